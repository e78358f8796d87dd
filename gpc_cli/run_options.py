"""The Lightning options every `gpc train ...` command shares, declared once."""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

from gpc.cli.limits import MAX_COUNT, MAX_PROCESSES, MAX_SEED
from gpc.tasks import task_names

Datasets = Annotated[list[Path], typer.Option("--dataset", "-d", help="Zarr episode store; repeat to train on several.")]
Out = Annotated[Path, typer.Option("--out", "-o", help="Run directory (checkpoints/, tensorboard/, run.json).")]


def _known_task(name: str) -> str:
    if name not in task_names():
        raise typer.BadParameter(f"unknown task {name!r} (known: {', '.join(task_names())})")
    return name


Task = Annotated[str, typer.Option("--task", help="Task the data comes from.", callback=_known_task)]
MaxSteps = Annotated[int | None, typer.Option("--max-steps", min=1, max=MAX_COUNT, help="Total optimiser steps (default: the profile's).")]
MaxEpochs = Annotated[int | None, typer.Option("--max-epochs", min=1, max=MAX_COUNT, help="Passes over the training windows.")]
BatchSize = Annotated[int | None, typer.Option("--batch-size", min=1, max=MAX_COUNT, help="Windows per step and device (default: the profile's).")]
Accelerator = Annotated[str, typer.Option("--accelerator", help="Lightning accelerator: cpu, gpu, auto.")]
Devices = Annotated[str, typer.Option("--devices", help="Devices per node: a number or auto.")]
Strategy = Annotated[str, typer.Option("--strategy", help="Lightning strategy, e.g. ddp (gloo on CPU).")]
NumNodes = Annotated[int, typer.Option("--num-nodes", min=1, max=MAX_PROCESSES, help="Machines.")]
Precision = Annotated[str, typer.Option("--precision", help="32-true, bf16-mixed, 16-mixed or bf16-auto (bf16-mixed where the hardware computes bf16 natively, else 32-true).")]
Seed = Annotated[int, typer.Option("--seed", min=0, max=MAX_SEED, help="Seed for weights, shuffling, noise and the validation split.")]
Resume = Annotated[bool, typer.Option("--resume", help="Continue the run in --out from its last checkpoint.")]
CheckpointEvery = Annotated[int, typer.Option("--checkpoint-every", min=1, max=MAX_COUNT, help="Steps between refreshes of last.ckpt.")]
CheckpointMinutes = Annotated[float, typer.Option("--checkpoint-minutes", min=0.01,
                                                  help="Also refresh last.ckpt once this many minutes have passed.")]
ValRatio = Annotated[float, typer.Option("--val-ratio", min=0.0, max=0.99, help="Share of episodes held out for validation.")]
ValEvery = Annotated[int | None, typer.Option("--val-every", min=1, max=MAX_COUNT, help="Steps between validations (default: each epoch).")]
NumWorkers = Annotated[int, typer.Option("--num-workers", min=0, max=MAX_PROCESSES, help="DataLoader worker processes.")]
Progress = Annotated[bool, typer.Option("--progress/--no-progress", help="Show the progress bar.")]




# The Lightning options every training command takes, with their defaults: declared once here.
RUN_OPTIONS: tuple[tuple[str, Any, Any], ...] = (
    ("max_steps", MaxSteps, None), ("max_epochs", MaxEpochs, None), ("batch_size", BatchSize, None),
    ("accelerator", Accelerator, "auto"), ("devices", Devices, "1"), ("strategy", Strategy, "auto"),
    ("num_nodes", NumNodes, 1), ("precision", Precision, "32-true"), ("seed", Seed, 0), ("resume", Resume, False),
    ("checkpoint_every", CheckpointEvery, 500), ("checkpoint_minutes", CheckpointMinutes, 10.0),
    ("val_every", ValEvery, None), ("val_ratio", ValRatio, 0.05), ("num_workers", NumWorkers, 0),
    ("progress", Progress, True),
)


def with_shared_options(spec: tuple[tuple[str, Any, Any], ...], key: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Give a command the options of ``spec`` (name, Annotated type, default) after its own; it receives
    their values as one dict in its parameter ``key``. Declares a family of options once for many commands."""

    def decorate(command: Callable[..., Any]) -> Callable[..., Any]:
        hints = typing.get_type_hints(command, include_extras=True)
        own = [p.replace(annotation=hints.get(p.name, p.annotation))
               for p in inspect.signature(command).parameters.values() if p.name != key]
        shared = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=kind)
                  for name, kind, default in spec]

        @functools.wraps(command)
        def wrapper(**kwargs: Any) -> Any:
            values = {name: kwargs.pop(name) for name, _, _ in spec}
            return command(**kwargs, **{key: values})

        del wrapper.__wrapped__  # Typer reads the signature below, not the wrapped function's
        wrapper.__signature__ = inspect.Signature(own + shared)  # type: ignore[attr-defined]
        wrapper.__annotations__ = {p.name: p.annotation for p in own + shared}
        return wrapper

    return decorate


# `gpc train ...` commands receive the Lightning options as ``options`` and pass them on to ``run_config``.
with_run_options = with_shared_options(RUN_OPTIONS, "options")


def run_config(profile: Any, out: Path, options: dict[str, Any] | None) -> Any:
    """The ``RunConfig`` the shared options describe (``Profile.run`` fills what was not given)."""
    assert options is not None  # with_run_options passes the Lightning options
    return profile.run(out, **options)


def echo_result(result: Any) -> None:
    if result.rank != 0:
        return
    best = (f"{result.best} (val loss {result.best_val_loss:.4f})"
            if result.best and result.best_val_loss is not None else "none")
    typer.echo(f"step {result.global_step}; last: {result.last}; best: {best}")
