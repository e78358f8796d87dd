"""The `gpc` command line: thin Typer commands over tasks/, datasets/ and models/."""

__version__ = "0.1.0"
