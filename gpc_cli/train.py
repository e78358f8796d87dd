"""`gpc train policy` and `gpc train value`: options parsed, then ``gpc.harness.training.train_component`` (the group
holds the others)."""

from __future__ import annotations

from pathlib import Path

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


@train_app.command("value")
@with_run_options
def value(
    dataset: Datasets,
    out: Out,
    task: Task = DEFAULT_TASK,
    policy: Path | None = typer.Option(None, "--policy", help="The policy it will rank for: its observations, goal mode, history and executed chunk are taken (default: state observations, 2 steps of history, chunks of 8)."),
    obs: str | None = typer.Option(None, "--obs", help="Observations: state, keypoints or image (default: the policy's, else state)."),
    profile: str = typer.Option("cpu", "--profile", help="cpu (two 256-wide layers), paper (512-wide), tiny (tests)."),
    lr: float | None = typer.Option(None, "--lr", min=0.0, help="Peak learning rate (default: the profile's, 3e-4)."),
    goal: str = typer.Option("fixed", "--goal", help="fixed or random (stores from `gpc collect --goal random`; default: the policy's)."),
    options: dict | None = None,
) -> None:
    """Train V-GPS's Q-function by IQL on Zarr stores (expert and exploration) with the task's reward; rank with
    `gpc eval POLICY --planner vgps --world-model OUT/checkpoints/last.ckpt`."""
    from gpc.harness.training import train_component
    from gpc.models.values.config import value_profile
    from gpc.models.values.module import ValueModule

    timeline = (2, 8)
    if policy is not None:
        from gpc.harness.policies import load_policy

        loaded = load_policy(policy, task, None)
        timeline = (loaded.config.n_obs_steps, loaded.config.n_action_steps)
        obs = obs or loaded.config.obs_type
        goal = "random" if loaded.config.encoder.goal and get_task(task).layout.goal is not None else goal
    chosen = value_profile(profile, obs or "state", get_task(task).layout, timeline, goal=goal, lr=lr)
    echo_result(train_component(ValueModule, chosen.config, dataset, run_config(chosen, out, options)))


if __name__ == "__main__":  # `python -m gpc.cli.train policy ...` (DDP re-launches this way)
    train_app()
