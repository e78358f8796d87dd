"""Bad input becomes one line on stderr and exit code 2, never a traceback."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

import typer
from typer.core import TyperGroup

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, KeyError, NotADirectoryError, PermissionError)


def fail(message: str) -> NoReturn:
    print(f"gpc: error: {message}", file=sys.stderr)
    raise SystemExit(2)


class OneLineErrors(TyperGroup):
    """The root command: user errors print one line (GPC_DEBUG=1 keeps the traceback)."""

    def main(self, args: Sequence[str] | None = None, prog_name: str | None = None, complete_var: str | None = None,
             standalone_mode: bool = True, windows_expand_args: bool = True, **extra: Any) -> Any:
        extra["complete_var"], extra["windows_expand_args"] = complete_var, windows_expand_args
        try:
            return super().main(args=args, prog_name=prog_name, standalone_mode=False, **extra)
        except typer.Abort:
            fail("aborted")
        except typer.Exit as exc:
            raise SystemExit(exc.exit_code) from None
        except typer.TyperException as exc:  # usage: unknown option, bad value, missing argument
            message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
            if type(exc).__name__ == "NoArgsIsHelpError":
                print(message)
                raise SystemExit(0) from None
            fail(" ".join(message.split()))
        except USER_ERRORS as exc:
            if os.environ.get("GPC_DEBUG"):
                raise
            msg = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc)
            fail(msg.splitlines()[0] if msg else type(exc).__name__)
