"""`gpc train world-model` and `gpc eval world-model`: thin Typer commands over ``models.world_model_*``.

``world_model_app`` holds both as ``train`` and ``eval``; the root CLI wires them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from gpc_cli.run_options import (
    Accelerator, BatchSize, CheckpointEvery, Datasets, Devices, MaxEpochs, MaxSteps, NumNodes, NumWorkers, Out,
    Precision, Progress, Resume, Seed, Strategy, Task, ValEvery, echo_result, run_config,
)

world_model_app = typer.Typer(help="Train and evaluate the state world model.", no_args_is_help=True)


@world_model_app.callback()
def _group() -> None:
    """Train and evaluate the state world model."""


@world_model_app.command("train")
def train(
    dataset: Datasets,
    out: Out,
    phase: int = typer.Option(1, "--phase", min=1, max=2, help="1: one-step loss; 2: unrolled loss from phase-1 weights."),
    init: Optional[Path] = typer.Option(None, "--init", help="Checkpoint to start from (phase 2: a phase-1 checkpoint; default: the latest in OUT's sibling *phase1 run)."),
    unroll: Optional[int] = typer.Option(None, "--unroll", min=2, help="Phase 2: predicted steps per unrolled segment (default: the horizon)."),
    task: Task = "pusht",
    obs: str = typer.Option("state", "--obs", help="Observations the model predicts (state; image follows)."),
    profile: str = typer.Option("cpu", "--profile", help="cpu (256x4 MLP, T=16) or tiny (tests)."),
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
    """Train the state world model (phase 1, then phase 2 from it); checkpoints land in OUT/checkpoints."""
    import dataclasses

    from models.world_model_config import world_model_profile
    from models.world_model_training import find_phase_one, train_world_model

    if obs != "state":
        raise typer.BadParameter(f"world model obs {obs!r}: only state is implemented so far", param_hint="--obs")
    if unroll is not None and phase != 2:
        raise typer.BadParameter("--unroll applies to phase 2", param_hint="--unroll")
    chosen = world_model_profile(profile, phase, task)
    config = dataclasses.replace(chosen.config, unroll=unroll)
    if phase == 2 and init is None and not resume:
        init = find_phase_one(out)
        typer.echo(f"phase 2 starts from {init}")
    run = run_config(
        out, chosen.max_steps, chosen.batch_size, max_steps=max_steps, max_epochs=max_epochs, batch_size=batch_size, task=task, accelerator=accelerator,
        devices=devices, strategy=strategy, num_nodes=num_nodes, precision=precision, seed=seed, resume=resume,
        progress=progress, checkpoint_every=checkpoint_every, val_every=val_every, num_workers=num_workers,
    )
    echo_result(train_world_model(config, dataset, run, init=init))


@world_model_app.command("eval")
def evaluate(
    checkpoint: Path = typer.Argument(..., help="World model checkpoint (its config and normaliser are inside)."),
    dataset: List[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store(s); with --split val, the stores it was trained on."),
    split: str = typer.Option("val", "--split", help="val: the held-out episodes of the training split; all: every episode."),
    episodes: Optional[int] = typer.Option(None, "--episodes", "-n", min=1, help="Only the first N of those episodes."),
    horizon: Optional[int] = typer.Option(None, "--horizon", min=1, help="Actions rolled out per window (default: the training horizon)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Directory for world_model_eval.json and .md (default: the run's eval/)."),
) -> None:
    """Open-loop rollout errors per horizon step on held-out windows, beside the nothing-moves baseline."""
    from models.world_model import WorldModelModule
    from models.world_model_eval import evaluate_rollouts, markdown_table
    from tasks import get_task

    module = WorldModelModule.load_from_checkpoint(checkpoint)
    geometry = get_task(module.config.task).geometry
    report = evaluate_rollouts(module, dataset, split=split, episodes=episodes, horizon=horizon,
                               vertices=geometry.TEE_BOXES.reshape(-1, 2))
    report["checkpoint"] = str(checkpoint)
    if out is None:
        out = checkpoint.parent.parent / "eval" if checkpoint.parent.name == "checkpoints" else checkpoint.parent / "eval"
    out.mkdir(parents=True, exist_ok=True)
    table = markdown_table(report, f"World model rollouts: {checkpoint}")
    (out / "world_model_eval.json").write_text(json.dumps(report, indent=2))
    (out / "world_model_eval.md").write_text(table)
    typer.echo(table + f"\nwrote {out / 'world_model_eval.json'} and {out / 'world_model_eval.md'}")


if __name__ == "__main__":  # `python -m gpc_cli.world_model train ...` (DDP re-launches this way)
    world_model_app()
