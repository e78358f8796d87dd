"""Bad input becomes one line on stderr and exit code 2, never a traceback; a stop says what was kept.

Exit codes: 0 done, 2 bad input or an operating-system error (the line names the path), 130 / 143
stopped by SIGINT / SIGTERM (the line says what was kept and how to go on).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

import typer
from typer.core import TyperGroup

from gpc.harness.interrupts import Interrupted, requested

USER_ERRORS = (ValueError, KeyError, OSError)


def fail(message: str, code: int = 2, kind: str = "error") -> NoReturn:
    print(f"gpc: {kind}: {message}", file=sys.stderr)
    raise SystemExit(code)


def one_line(exc: BaseException) -> str:
    """The first line of an error, with the path an OS error concerns (``[Errno 30] ...`` names none)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        return f"{where}: {exc.strerror}" if where else exc.strerror
    msg = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc)
    return msg.strip().splitlines()[0] if msg.strip() else type(exc).__name__


class OneLineErrors(TyperGroup):
    """The root command: user errors print one line (GPC_DEBUG=1 keeps the traceback)."""

    def main(self, args: Sequence[str] | None = None, prog_name: str | None = None, complete_var: str | None = None,
             standalone_mode: bool = True, windows_expand_args: bool = True, **extra: Any) -> Any:
        extra["complete_var"], extra["windows_expand_args"] = complete_var, windows_expand_args
        try:
            done = super().main(args=args, prog_name=prog_name, standalone_mode=False, **extra)
            signum = requested()
            if signum is not None:  # a short command that had no safe point to stop at: still not exit 0
                raise Interrupted(signum, "the command finished before it could stop; what it wrote is complete")
            return done
        except typer.Abort:
            fail("stopped before finishing; nothing was left half written", 130, "stopped by SIGINT")
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
            fail(one_line(exc))
        except Interrupted as stop:
            fail(stop.kept or "stopped; nothing was left half written", stop.exit_code, f"stopped by {stop.name}")
