"""`gpc train ...`: thin Typer commands over ``models.training``."""

from __future__ import annotations

import dataclasses
from typing import Optional

import typer

from gpc_cli.run_options import (
    Accelerator, BatchSize, CheckpointEvery, Datasets, Devices, MaxEpochs, MaxSteps, NumNodes, NumWorkers, Out,
    Precision, Progress, Resume, Seed, Strategy, Task, ValEvery, echo_result, run_config,
)

train_app = typer.Typer(help="Train the policy (world models and rewards follow).", no_args_is_help=True)


@train_app.callback()
def _group() -> None:
    """Train the policy (world models and rewards follow)."""


@train_app.command("policy")
def policy(
    dataset: Datasets,
    out: Out,
    task: Task = "pusht",
    obs: str = typer.Option("state", "--obs", help="Observations: state, keypoints or image."),
    profile: str = typer.Option("cpu", "--profile", help="cpu (narrow U-Net, DDIM-10), paper (Diffusion Policy's sizes), tiny (tests)."),
    lr: Optional[float] = typer.Option(None, "--lr", min=0.0, help="Peak learning rate (default: the profile's, Diffusion Policy's 1e-4)."),
    max_steps: MaxSteps = None,
    max_epochs: MaxEpochs = None,
    batch_size: BatchSize = None,
    accelerator: Accelerator = "auto",
    devices: Devices = "1",
    strategy: Strategy = "auto",
    num_nodes: NumNodes = 1,
    precision: Precision = "32-true",
    seed: Seed = 0,
    resume: Resume = False,
    checkpoint_every: CheckpointEvery = 500,
    val_every: ValEvery = None,
    num_workers: NumWorkers = 0,
    progress: Progress = True,
) -> None:
    """Train Diffusion Policy on Zarr stores; best and last checkpoints land in OUT/checkpoints."""
    from models.policy_config import policy_profile
    from models.training import train_policy

    chosen = policy_profile(profile, obs, task)
    policy_config = chosen.policy
    if lr is not None:
        policy_config = dataclasses.replace(policy_config, optim=dataclasses.replace(policy_config.optim, lr=lr))
    run = run_config(
        out, chosen.max_steps, chosen.batch_size, max_steps=max_steps, max_epochs=max_epochs, batch_size=batch_size, task=task, accelerator=accelerator,
        devices=devices, strategy=strategy, num_nodes=num_nodes, precision=precision, seed=seed, resume=resume,
        progress=progress, checkpoint_every=checkpoint_every, val_every=val_every, num_workers=num_workers,
    )
    echo_result(train_policy(policy_config, dataset, run))


if __name__ == "__main__":  # `python -m gpc_cli.train policy ...` (DDP re-launches this way)
    train_app()
