"""The one error type for bad data on disk, so the CLI can report it as a single line."""


class DataError(ValueError):
    """A store, key or value that cannot be used; the message names the file or key."""
