"""A command group whose first argument may also be the default command's (``gpc eval CKPT``)."""

from __future__ import annotations

from typing import Any

from typer.core import TyperGroup


class DefaultToRun(TyperGroup):
    """``gpc eval CKPT ...`` means ``gpc eval run CKPT ...``; named sub-commands still win."""

    default_command = "run"

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h"):
            args = [self.default_command, *args]
        return super().parse_args(ctx, args)
