"""`gpc train reward` and `gpc eval reward`: options parsed, then ``gpc.harness.training.train_component`` and
``gpc.harness.model_eval.evaluate_reward``; the root CLI wires both."""

from __future__ import annotations

from pathlib import Path

import typer

from gpc.cli.limits import MAX_COUNT
from gpc.cli.run_options import Datasets, Out, Task, echo_result, run_config, with_run_options
from gpc.tasks import DEFAULT_TASK, get_task

reward_app = typer.Typer(help="Train and evaluate the learned image reward.", no_args_is_help=True)


@reward_app.callback()
def _group() -> None:
    """Train and evaluate the learned image reward."""


@reward_app.command("train")
@with_run_options
def train(
    dataset: Datasets,
    out: Out,
    task: Task = DEFAULT_TASK,
    profile: str = typer.Option("cpu", "--profile", help="cpu (ResNet18 width 32, 64 px), paper (full ResNet18, 96 px), tiny (tests)."),
    image_size: int | None = typer.Option(None, "--image-size", min=8, max=MAX_COUNT, help="Frame size the network reads (default: the profile's); match the world model's frames."),
    lr: float | None = typer.Option(None, "--lr", min=0.0, help="Peak learning rate (default: the profile's)."),
    options: dict | None = None,
) -> None:
    """Train the image reward's pose predictor on the frames of Zarr stores, labelled by their recorded states."""
    from gpc.harness.training import train_component
    from gpc.models.rewards.learned import RewardPredictorModule, reward_profile

    spec = get_task(task)
    chosen = reward_profile(profile, spec.layout, input_size=image_size, lr=lr, state_reward=spec.state_reward)
    echo_result(train_component(RewardPredictorModule, chosen.config, dataset, run_config(chosen, out, options)))


@reward_app.command("eval")
def evaluate(
    checkpoint: Path = typer.Argument(..., help="Reward checkpoint (its config and normaliser are inside)."),
    dataset: list[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store(s); with --split val, the stores it was trained on, in the same order."),
    split: str = typer.Option("val", "--split", help="val: the held-out episodes of the training split; all: every episode."),
    ood: list[Path] = typer.Option([], "--ood", help="Also evaluate every episode of this store, never trained on (e.g. the human data); repeatable."),
    episodes: int | None = typer.Option(None, "--episodes", "-n", min=1, max=MAX_COUNT, help="Only the first N episodes of each evaluated set."),
    stride: int = typer.Option(1, "--stride", min=1, max=MAX_COUNT, help="Every k-th frame of each episode."),
    image_size: int | None = typer.Option(None, "--image-size", min=8, max=MAX_COUNT, help="Downscale frames to this size first (as a world model would produce them)."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Directory for reward_eval.json and .md (default: the run's eval/)."),
) -> None:
    """Predicted vs true registration loss (px) and pose errors on held-out frames (and out-of-distribution stores)."""
    from gpc.harness.model_eval import evaluate_reward

    written = evaluate_reward(checkpoint, dataset, out, split=split, ood=ood, episodes=episodes, stride=stride,
                              image_size=image_size)
    typer.echo(written.markdown + f"\nwrote {' and '.join(map(str, written.files))}")


if __name__ == "__main__":  # `python -m gpc.cli.reward train ...` (DDP re-launches this way)
    reward_app()
