"""`gpc train policy` and `gpc train value`: options parsed, then ``gpc.harness.training.train_component`` (the group
holds the others)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Any

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
    labels: str = typer.Option("action", "--labels", help="action: learn the actions that ran; expert_action: a DART store's labels (`gpc collect --dart`), the actions of stores without them."),
    obs_mlp: str = typer.Option("", "--obs-mlp", help="Widths of an MLP over each step's observations, e.g. 256,256 (default: none, as Diffusion Policy): lets a policy that reads a goal relate it to the scene before the U-Net."),
    options: dict | None = None,
) -> None:
    """Train Diffusion Policy on Zarr stores; best and last checkpoints land in OUT/checkpoints."""
    from gpc.harness.training import train_component
    from gpc.models.policy.config import policy_profile
    from gpc.models.policy.module import PolicyModule

    try:
        widths = tuple(int(w) for w in obs_mlp.split(",") if w.strip())
    except ValueError:
        raise typer.BadParameter(f"{obs_mlp!r}: use widths joined by commas, e.g. 256,256", param_hint="--obs-mlp") from None
    chosen = policy_profile(profile, obs, get_task(task).layout, goal=goal, lr=lr, mlp=widths)
    chosen = dataclasses.replace(chosen, config=dataclasses.replace(chosen.config, labels=labels))
    echo_result(train_component(PolicyModule, chosen.config, dataset, run_config(chosen, out, options)))


PolicyOption = Annotated[Path | None, typer.Option("--policy", help="The policy it will rank for: its observations, goal mode, history and executed chunk are taken (default: state observations, 2 steps of history, chunks of 8).")]
ObsOption = Annotated[str | None, typer.Option("--obs", help="Observations: state, keypoints or image (default: the policy's, else state).")]
GoalOption = Annotated[str, typer.Option("--goal", help="fixed or random (stores from `gpc collect --goal random`; default: the policy's).")]
LrOption = Annotated[float | None, typer.Option("--lr", min=0.0, help="Peak learning rate (default: the profile's).")]


def _for_policy(policy: Path | None, task: str, obs: str | None, goal: str) -> tuple[str, str, tuple[int, int]]:
    """(observations, goal mode, (history, executed chunk)) of the policy a baseline ranks for, or the defaults."""
    if policy is None:
        return obs or "state", goal, (2, 8)
    from gpc.harness.policies import load_policy

    loaded = load_policy(policy, task, None)
    varies = loaded.config.encoder.goal and get_task(task).layout.goal is not None
    return obs or loaded.config.obs_type, "random" if varies else goal, (loaded.config.n_obs_steps, loaded.config.n_action_steps)


@train_app.command("value")
@with_run_options
def value(
    dataset: Datasets,
    out: Out,
    task: Task = DEFAULT_TASK,
    policy: PolicyOption = None,
    obs: ObsOption = None,
    profile: str = typer.Option("cpu", "--profile", help="cpu (two 256-wide layers), paper (512-wide), tiny (tests)."),
    lr: LrOption = None,
    goal: GoalOption = "fixed",
    expectile: float | None = typer.Option(None, "--expectile", help="IQL's tau, in (0, 1): the expectile of Q that V fits (profile: 0.7; higher is closer to a max over the data's chunks)."),
    discount: float | None = typer.Option(None, "--discount", help="Discount per environment step, in [0, 1) (profile: 0.99)."),
    options: dict | None = None,
) -> None:
    """Train V-GPS's Q-function by IQL on Zarr stores (expert and exploration) with the task's reward; rank with
    `gpc eval POLICY --planner vgps --world-model OUT/checkpoints/last.ckpt`."""
    from gpc.harness.training import train_component
    from gpc.models.values.config import value_profile
    from gpc.models.values.module import ValueModule

    obs_type, goal, timeline = _for_policy(policy, task, obs, goal)
    chosen = value_profile(profile, obs_type, get_task(task).layout, timeline, goal=goal, lr=lr)
    config = chosen.config
    try:
        config = dataclasses.replace(config, expectile=config.expectile if expectile is None else expectile,
                                     discount=config.discount if discount is None else discount)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--" + str(exc).split()[0]) from None
    chosen = dataclasses.replace(chosen, config=config)
    echo_result(train_component(ValueModule, chosen.config, dataset, run_config(chosen, out, options)))


@train_app.command("latent-world-model")
@with_run_options
def latent_world_model(
    dataset: Datasets,
    out: Out,
    task: Task = DEFAULT_TASK,
    kind: str = typer.Option("rssm", "--kind", help="rssm: DreamerV3-style (--planner dreamer); ladi: LaDi-WM-style diffusion over the policy's frozen encoder's latents (--planner ladi; needs --policy)."),
    policy: PolicyOption = None,
    obs: ObsOption = None,
    profile: str = typer.Option("cpu", "--profile", help="cpu, paper (DreamerV3's medium sizes; Diffusion Policy's U-Net), tiny (tests)."),
    lr: LrOption = None,
    goal: GoalOption = "fixed",
    history: int | None = typer.Option(None, "--history", min=1, help="rssm: observations each posterior reads, stacked (profile: 1, DreamerV3's; the policy's history, 2, lets a decision's first posterior see velocities)."),
    options: dict | None = None,
) -> None:
    """Train a latent world model on Zarr stores with the task's reward; rank with
    `gpc eval POLICY --planner dreamer|ladi --world-model OUT/checkpoints/last.ckpt`."""
    from gpc.harness.training import train_component

    layout = get_task(task).layout
    if kind == "rssm":
        from gpc.models.latent.config import latent_profile
        from gpc.models.latent.module import LatentWorldModelModule

        obs_type, goal, _ = _for_policy(policy, task, obs, goal)
        chosen: Any = latent_profile(profile, obs_type, layout, goal=goal, lr=lr)
        if history is not None:
            chosen = dataclasses.replace(chosen, config=dataclasses.replace(chosen.config, history=history))
        cls: Any = LatentWorldModelModule
    elif kind == "ladi":
        from gpc.harness.policies import load_policy
        from gpc.models.ladi.config import ladi_profile
        from gpc.models.ladi.module import LadiModule

        if history is not None:
            raise typer.BadParameter("--kind ladi reads the policy's history", param_hint="--history")
        if policy is None:
            raise typer.BadParameter("the LaDi-WM-style model reads the policy's frozen encoder: give --policy", param_hint="--policy")
        loaded = load_policy(policy, task, None)
        if loaded.source.get("format", "gpc") != "gpc":
            raise typer.BadParameter("--kind ladi reads a gpc policy checkpoint's encoder", param_hint="--policy")
        timeline = (loaded.config.n_obs_steps, loaded.config.n_action_steps)
        chosen, cls = ladi_profile(profile, layout, str(policy), loaded.config.encoder, timeline, lr=lr), LadiModule
    else:
        raise typer.BadParameter(f"{kind!r}: use rssm or ladi", param_hint="--kind")
    echo_result(train_component(cls, chosen.config, dataset, run_config(chosen, out, options)))


if __name__ == "__main__":  # `python -m gpc.cli.train policy ...` (DDP re-launches this way)
    train_app()
