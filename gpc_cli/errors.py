"""Bad input becomes one line on stderr and exit code 2, never a traceback."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import typer

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, KeyError, NotADirectoryError, PermissionError)


class UsageProblem(ValueError):
    """Raised by commands for a bad option value; the message names the option."""


def fail(message: str) -> "NoReturn":  # noqa: F821 - typing only
    print(f"gpc: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_import_layout() -> None:
    """Refuse to run against Hugging Face's ``datasets`` (a name clash of the user's layout)."""
    import datasets

    here = Path(__file__).resolve().parent.parent
    origin = Path(getattr(datasets, "__file__", "") or "").resolve()
    if here not in origin.parents:
        fail(
            f"the package 'datasets' resolves to {origin}, not gpc's; run gpc from its own virtual "
            "environment (make venv) where Hugging Face's datasets is not installed"
        )


def run(app: typer.Typer, argv: list[str] | None = None) -> None:
    """Invoke ``app``; user errors print one line (set GPC_DEBUG=1 for the traceback)."""
    try:
        typer.main.get_command(app).main(args=argv, prog_name="gpc", standalone_mode=False)
    except typer.Abort:
        fail("aborted")
    except typer.Exit as exc:
        raise SystemExit(exc.exit_code) from None
    except typer.TyperException as exc:  # usage errors: unknown option, bad value, missing argument
        message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
        if type(exc).__name__ == "NoArgsIsHelpError":
            print(message)
            raise SystemExit(0) from None
        fail(" ".join(message.split()))
    except USER_ERRORS as exc:
        if os.environ.get("GPC_DEBUG"):
            raise
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
        fail(str(msg).splitlines()[0] if str(msg) else type(exc).__name__)
