"""The Lightning options every `gpc train ...` command shares, declared once."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, List, Optional

import typer

from tasks import TASKS

Datasets = Annotated[List[Path], typer.Option("--dataset", "-d", help="Zarr episode store; repeat to train on several.")]
Out = Annotated[Path, typer.Option("--out", "-o", help="Run directory (checkpoints/, tensorboard/, run.json).")]
Task = Annotated[str, typer.Option("--task", help="Task the data comes from.")]
MaxSteps = Annotated[Optional[int], typer.Option("--max-steps", min=1, help="Total optimiser steps (default: the profile's).")]
MaxEpochs = Annotated[Optional[int], typer.Option("--max-epochs", min=1, help="Passes over the training windows.")]
BatchSize = Annotated[Optional[int], typer.Option("--batch-size", min=1, help="Windows per step and device (default: the profile's).")]
Accelerator = Annotated[str, typer.Option("--accelerator", help="Lightning accelerator: cpu, gpu, auto.")]
Devices = Annotated[str, typer.Option("--devices", help="Devices per node: a number or auto.")]
Strategy = Annotated[str, typer.Option("--strategy", help="Lightning strategy, e.g. ddp (gloo on CPU).")]
NumNodes = Annotated[int, typer.Option("--num-nodes", min=1, help="Machines.")]
Precision = Annotated[str, typer.Option("--precision", help="32-true, bf16-mixed or 16-mixed.")]
Seed = Annotated[int, typer.Option("--seed", min=0, help="Seed for weights, shuffling, noise and the validation split.")]
Resume = Annotated[bool, typer.Option("--resume", help="Continue the run in --out from its last checkpoint.")]
CheckpointEvery = Annotated[int, typer.Option("--checkpoint-every", min=1, help="Steps between refreshes of last.ckpt.")]
ValEvery = Annotated[Optional[int], typer.Option("--val-every", min=1, help="Steps between validations (default: each epoch).")]
NumWorkers = Annotated[int, typer.Option("--num-workers", min=0, help="DataLoader worker processes.")]
Progress = Annotated[bool, typer.Option("--progress/--no-progress", help="Show the progress bar.")]




def run_config(out: Path, default_steps: int, default_batch: int, *, max_steps: int | None, max_epochs: int | None,
               batch_size: int | None, task: str, **lightning: Any):
    """A ``RunConfig`` from the shared options, the profile filling what was not given."""
    from models.training import RunConfig

    if task not in TASKS:
        raise typer.BadParameter(f"unknown task {task!r} (known: {', '.join(TASKS)})", param_hint="--task")
    return RunConfig(run_dir=out, max_steps=max_steps if max_steps or max_epochs else default_steps,
                     max_epochs=max_epochs, batch_size=batch_size or default_batch, **lightning)


def echo_result(result: Any) -> None:
    if result.rank != 0:
        return
    best = (f"{result.best} (val loss {result.best_val_loss:.4f})"
            if result.best and result.best_val_loss is not None else "none")
    typer.echo(f"step {result.global_step}; last: {result.last}; best: {best}")
