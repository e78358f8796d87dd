"""`gpc train policy`: options parsed, then ``gpc.harness.training.train_component`` (the group holds the others)."""

from __future__ import annotations

import dataclasses

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

    if goal not in ("fixed", "random"):
        raise typer.BadParameter(f"goal {goal!r}: use fixed or random", param_hint="--goal")
    chosen = policy_profile(profile, obs, get_task(task).layout)
    policy_config = chosen.config
    if goal == "random":
        policy_config = dataclasses.replace(policy_config, encoder=dataclasses.replace(policy_config.encoder, goal=True))
    if lr is not None:
        policy_config = dataclasses.replace(policy_config, optim=dataclasses.replace(policy_config.optim, lr=lr))
    assert options is not None  # with_run_options passes the Lightning options
    run = run_config(out, chosen.max_steps, chosen.batch_size, task=task, **options)
    echo_result(train_component(PolicyModule, policy_config, dataset, run))


if __name__ == "__main__":  # `python -m gpc.cli.train policy ...` (DDP re-launches this way)
    train_app()
