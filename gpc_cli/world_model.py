"""`gpc train world-model` and `gpc eval world-model`: options parsed, then ``gpc.harness.training.train_component``
and ``gpc.harness.model_eval.evaluate_world_model``; the root CLI wires both."""

from __future__ import annotations

from pathlib import Path

import typer

from gpc.cli.limits import MAX_COUNT
from gpc.cli.run_options import Datasets, Out, Task, echo_result, run_config, with_run_options
from gpc.tasks import DEFAULT_TASK, get_task

world_model_app = typer.Typer(help="Train and evaluate world models (state or image).", no_args_is_help=True)


@world_model_app.callback()
def _group() -> None:
    """Train and evaluate world models (state or image)."""


@world_model_app.command("train")
@with_run_options
def train(
    dataset: Datasets,
    out: Out,
    phase: int = typer.Option(1, "--phase", min=1, max=2, help="1: one-step loss; 2: unrolled loss from phase-1 weights."),
    init: Path | None = typer.Option(None, "--init", help="Checkpoint to start from (phase 2: a phase-1 checkpoint; default: the latest in OUT's sibling *phase1 run)."),
    unroll: int | None = typer.Option(None, "--unroll", min=2, max=MAX_COUNT, help="Phase 2: predicted steps per unrolled segment (default: the horizon)."),
    task: Task = DEFAULT_TASK,
    obs: str = typer.Option("state", "--obs", help="Observations the model predicts: state (MLP) or image (EDM U-Net)."),
    profile: str = typer.Option("cpu", "--profile", help="state: cpu (256x4 MLP, T=16) or tiny; image: cpu (48 px, frameskip 4), paper (96 px, GPU) or tiny."),
    frame: str | None = typer.Option(None, "--frame", help="State models: object (also see the scene from the object's frame; the default when it has an angle) or world (world coordinates only)."),
    feedback: str | None = typer.Option(None, "--feedback", help="Image phase 2: frames fed back as context, denoised (one-step estimate, default) or sampled."),
    distill: Path | None = typer.Option(None, "--distill", help="Image models: a trained model to distil into a student sampling in --sampler-steps (starts from its weights)."),
    sampler_steps: int = typer.Option(1, "--sampler-steps", min=1, max=MAX_COUNT, help="--distill: the student's Euler steps per predicted frame."),
    options: dict | None = None,
) -> None:
    """Train a world model (phase 1, then phase 2 from it; or a fewer-step student of one); checkpoints land in OUT/checkpoints."""
    from gpc.harness.training import train_component
    from gpc.models.world_models.module import WorldModelModule, find_phase_one, load_world_model
    from gpc.models.world_models.profiles import distill_profile, world_model_profile

    if distill is not None:
        if init is not None:
            raise typer.BadParameter("a student starts from its teacher's weights; drop --init", param_hint="--init")
        chosen = distill_profile(profile, load_world_model(distill, task).config, str(distill), sampler_steps)
    else:
        chosen = world_model_profile(profile, phase, get_task(task).layout, obs, frame, unroll=unroll, feedback=feedback)
    run = run_config(chosen, out, options)
    if distill is not None and not run.resume:
        init = distill
    if phase == 2 and init is None and not run.resume:
        init = find_phase_one(out)
        typer.echo(f"phase 2 starts from {init}")
    echo_result(train_component(WorldModelModule, chosen.config, dataset, run, init=init))


@world_model_app.command("eval")
def evaluate(
    checkpoint: Path = typer.Argument(..., help="World model checkpoint (its config and normaliser are inside)."),
    dataset: list[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store(s); with --split val, the stores it was trained on."),
    split: str = typer.Option("val", "--split", help="val: the held-out episodes of the training split; all: every episode."),
    episodes: int | None = typer.Option(None, "--episodes", "-n", min=1, max=MAX_COUNT, help="Only the first N of those episodes."),
    horizon: int | None = typer.Option(None, "--horizon", min=1, max=MAX_COUNT, help="Actions rolled out per window (default: the training horizon)."),
    stride: int | None = typer.Option(None, "--stride", min=1, max=MAX_COUNT, help="Steps between window starts (default: 1 for state, 8 for image models)."),
    max_windows: int = typer.Option(512, "--max-windows", min=1, max=MAX_COUNT, help="Image models: at most this many windows, evenly spread."),
    noise: str = typer.Option("frozen", "--noise", help="Image models: frozen (deterministic) or sampled initial noise."),
    sampler_steps: int | None = typer.Option(None, "--sampler-steps", min=1, max=MAX_COUNT, help="Image models: Euler steps per predicted frame (default: the checkpoint's, 3)."),
    pose_reader: Path | None = typer.Option(None, "--pose-reader", help="Image models: read the objects' poses with this `gpc train reward` checkpoint (what the learned reward sees) instead of by colour; a state reader (a task scored by its own state reward) reads the whole state, heights included."),
    held_out_of: Path | None = typer.Option(None, "--held-out-of", help="Use the episodes this other checkpoint held out (among --dataset) instead: two models on one unseen set; refused where this model trained on one of them."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Directory for world_model_eval.json and .md (default: the run's eval/)."),
) -> None:
    """Open-loop rollout errors per horizon step on held-out windows, beside the nothing-moves baseline.

    Image models: SSIM and PSNR per predicted frame, the block pose read from the frames by
    colour against the recorded frames' (on windows where the block moves), the share of
    predicted frames where the agent is visible, and a PNG grid of recorded over predicted frames.
    """
    from gpc.harness.model_eval import evaluate_world_model

    written = evaluate_world_model(checkpoint, dataset, out, split=split, episodes=episodes, horizon=horizon,
                                   stride=stride, max_windows=max_windows, noise=noise, sampler_steps=sampler_steps,
                                   pose_reader=pose_reader, held_out_of=held_out_of)
    typer.echo(written.markdown + f"\nwrote {', '.join(map(str, written.files))}")


if __name__ == "__main__":  # `python -m gpc.cli.world_model train ...` (DDP re-launches this way)
    world_model_app()
