"""`gpc train ...`: thin Typer commands over ``models.training``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

TASKS = ("pusht",)

train_app = typer.Typer(help="Train the policy (world models and rewards follow).", no_args_is_help=True)


@train_app.callback()
def _group() -> None:
    """Train the policy (world models and rewards follow)."""


@train_app.command("policy")
def policy(
    dataset: List[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store; repeat to train on several."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory (checkpoints/, tensorboard/, run.json)."),
    task: str = typer.Option("pusht", "--task", help="Task the data comes from."),
    obs: str = typer.Option("state", "--obs", help="Observations: state, keypoints or image."),
    profile: str = typer.Option("cpu", "--profile", help="cpu (narrow U-Net, DDIM-10), paper (Diffusion Policy's sizes), tiny (tests)."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", min=1, help="Total optimiser steps (default: the profile's)."),
    max_epochs: Optional[int] = typer.Option(None, "--max-epochs", min=1, help="Passes over the training windows."),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", min=1, help="Windows per step and device (default: the profile's)."),
    accelerator: str = typer.Option("auto", "--accelerator", help="Lightning accelerator: cpu, gpu, auto."),
    devices: str = typer.Option("1", "--devices", help="Devices per node: a number or auto."),
    strategy: str = typer.Option("auto", "--strategy", help="Lightning strategy, e.g. ddp (gloo on CPU)."),
    num_nodes: int = typer.Option(1, "--num-nodes", min=1, help="Machines."),
    precision: str = typer.Option("32-true", "--precision", help="32-true, bf16-mixed or 16-mixed."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed for weights, shuffling and noise."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in --out from its last checkpoint."),
    checkpoint_every: int = typer.Option(500, "--checkpoint-every", min=1, help="Steps between refreshes of last.ckpt."),
    val_every: Optional[int] = typer.Option(None, "--val-every", min=1, help="Steps between validations (default: each epoch)."),
    num_workers: int = typer.Option(0, "--num-workers", min=0, help="DataLoader worker processes."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show the progress bar."),
) -> None:
    """Train Diffusion Policy on Zarr stores; best and last checkpoints land in OUT/checkpoints."""
    from models.policy_config import policy_profile
    from models.training import RunConfig, train_policy

    if task not in TASKS:
        raise typer.BadParameter(f"unknown task {task!r} (known: {', '.join(TASKS)})", param_hint="--task")
    chosen = policy_profile(profile, obs, task)
    run = RunConfig(
        run_dir=out, max_steps=max_steps if max_steps or max_epochs else chosen.max_steps, max_epochs=max_epochs,
        batch_size=batch_size or chosen.batch_size, accelerator=accelerator, devices=devices, strategy=strategy,
        num_nodes=num_nodes, precision=precision, seed=seed, resume=resume, progress=progress,
        checkpoint_every=checkpoint_every, val_every=val_every, num_workers=num_workers,
    )
    result = train_policy(chosen.policy, dataset, run)
    best = f"{result.best} (val loss {result.best_val_loss:.4f})" if result.best and result.best_val_loss is not None else "none"
    if result.rank == 0:
        typer.echo(f"step {result.global_step}; last: {result.last}; best: {best}")


if __name__ == "__main__":  # `python -m gpc_cli.train policy ...` (DDP re-launches this way)
    train_app()
