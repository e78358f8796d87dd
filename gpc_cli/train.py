"""`gpc train policy`: options parsed, then ``gpc.harness.training.train_component`` (the group holds the others)."""

from __future__ import annotations

import typer

from gpc.cli.run_options import Datasets, Out, Task, echo_result, run_config, with_run_options
from gpc.tasks import DEFAULT_TASK, get_task

train_app = typer.Typer(help="Train the policy (world models and rewards follow).", no_args_is_help=True)


@train_app.callback()
def _group() -> None:
    """Train the policy (world models and rewards follow)."""


@train_app.command("policy")
@with_run_options
def policy(
    dataset: Datasets,
    out: Out,
    task: Task = DEFAULT_TASK,
    obs: str = typer.Option("state", "--obs", help="Observations: state, keypoints or image."),
    profile: str = typer.Option("cpu", "--profile", help="cpu (narrow U-Net, DDIM-10), paper (Diffusion Policy's sizes), tiny (tests)."),
    lr: float | None = typer.Option(None, "--lr", min=0.0, help="Peak learning rate (default: the profile's, Diffusion Policy's 1e-4)."),
    goal: str = typer.Option("fixed", "--goal", help="fixed: one goal for all episodes; random: the policy also reads each episode's goal (stores from `gpc collect --goal random`)."),
    options: dict | None = None,
) -> None:
    """Train Diffusion Policy on Zarr stores; best and last checkpoints land in OUT/checkpoints."""
    from gpc.harness.training import train_component
    from gpc.models.policy.config import policy_profile
    from gpc.models.policy.module import PolicyModule

    chosen = policy_profile(profile, obs, get_task(task).layout, goal=goal, lr=lr)
    echo_result(train_component(PolicyModule, chosen.config, dataset, run_config(chosen, out, options)))


if __name__ == "__main__":  # `python -m gpc.cli.train policy ...` (DDP re-launches this way)
    train_app()
