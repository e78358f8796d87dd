"""`gpc train reward` and `gpc eval reward`: thin Typer commands over ``models.reward_predictor`` / ``reward_training``.

``reward_app`` holds both as ``train`` and ``eval``; the root CLI wires them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import List, Optional

import typer

from gpc_cli.run_options import Datasets, Out, Task, echo_result, run_config, with_run_options

reward_app = typer.Typer(help="Train and evaluate the learned image reward.", no_args_is_help=True)


@reward_app.callback()
def _group() -> None:
    """Train and evaluate the learned image reward."""


@reward_app.command("train")
@with_run_options
def train(
    dataset: Datasets,
    out: Out,
    task: Task = "pusht",
    profile: str = typer.Option("cpu", "--profile", help="cpu (ResNet18 width 32, 64 px), paper (full ResNet18, 96 px), tiny (tests)."),
    image_size: Optional[int] = typer.Option(None, "--image-size", min=8, help="Frame size the network reads (default: the profile's); match the world model's frames."),
    lr: Optional[float] = typer.Option(None, "--lr", min=0.0, help="Peak learning rate (default: the profile's)."),
    options: dict | None = None,
) -> None:
    """Train the image reward's pose predictor on the frames of Zarr stores, labelled by their recorded states."""
    from models.reward_predictor import reward_profile
    from models.reward_training import train_reward_predictor
    from tasks import get_task

    chosen = reward_profile(profile, task)
    geometry = get_task(task).geometry
    config = chosen.config.with_task(geometry.TEE_BOXES.reshape(-1, 2), geometry.GOAL_POSE, geometry.WORKSPACE)
    if image_size is not None:
        config = dataclasses.replace(config, input_size=image_size)
    if lr is not None:
        config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=lr))
    run = run_config(out, chosen.max_steps, chosen.batch_size, task=task, **options)
    echo_result(train_reward_predictor(config, dataset, run))


@reward_app.command("eval")
def evaluate(
    checkpoint: Path = typer.Argument(..., help="Reward checkpoint (its config and normaliser are inside)."),
    dataset: List[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store(s); with --split val, the stores it was trained on, in the same order."),
    split: str = typer.Option("val", "--split", help="val: the held-out episodes of the training split; all: every episode."),
    ood: List[Path] = typer.Option([], "--ood", help="Also evaluate every episode of this store, never trained on (e.g. the human data); repeatable."),
    episodes: Optional[int] = typer.Option(None, "--episodes", "-n", min=1, help="Only the first N episodes of each evaluated set."),
    stride: int = typer.Option(1, "--stride", min=1, help="Every k-th frame of each episode."),
    image_size: Optional[int] = typer.Option(None, "--image-size", min=8, help="Downscale frames to this size first (as a world model would produce them)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Directory for reward_eval.json and .md (default: the run's eval/)."),
) -> None:
    """Predicted vs true registration loss (px) and pose errors on held-out frames (and out-of-distribution stores)."""
    from models.reward_predictor import RewardPredictorModule
    from models.reward_training import evaluate_reward_predictor, markdown_report

    module = RewardPredictorModule.load_from_checkpoint(checkpoint)
    sets = [(list(dataset), split)] + [([p], "all") for p in ood]
    reports = []
    for paths, which in sets:
        report = evaluate_reward_predictor(module, paths, split=which, episodes=episodes, stride=stride, frame_size=image_size)
        report["checkpoint"] = str(checkpoint)
        reports.append(report)
    if out is None:
        out = checkpoint.parent.parent / "eval" if checkpoint.parent.name == "checkpoints" else checkpoint.parent / "eval"
    out.mkdir(parents=True, exist_ok=True)
    table = markdown_report(reports, f"Image reward: {checkpoint}")
    (out / "reward_eval.json").write_text(json.dumps(reports, indent=2))
    (out / "reward_eval.md").write_text(table)
    typer.echo(table + f"\nwrote {out / 'reward_eval.json'} and {out / 'reward_eval.md'}")


if __name__ == "__main__":  # `python -m gpc_cli.reward train ...` (DDP re-launches this way)
    reward_app()
