"""`gpc train world-model` and `gpc eval world-model`: thin Typer commands over ``models.world_model_*``
and ``models.visual_world_model*``.

``world_model_app`` holds both as ``train`` and ``eval``; the root CLI wires them. The eval
command fills the visual readout (block and agent colours, the T's axis) from the task's renderer.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import List, Optional

import typer

from gpc_cli.run_options import Datasets, Out, Task, echo_result, run_config, with_run_options

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
    init: Optional[Path] = typer.Option(None, "--init", help="Checkpoint to start from (phase 2: a phase-1 checkpoint; default: the latest in OUT's sibling *phase1 run)."),
    unroll: Optional[int] = typer.Option(None, "--unroll", min=2, help="Phase 2: predicted steps per unrolled segment (default: the horizon)."),
    task: Task = "pusht",
    obs: str = typer.Option("state", "--obs", help="Observations the model predicts: state (MLP) or image (EDM U-Net)."),
    profile: str = typer.Option("cpu", "--profile", help="state: cpu (256x4 MLP, T=16) or tiny; image: cpu (48 px, frameskip 4), paper (96 px, GPU) or tiny."),
    frame: str = typer.Option("object", "--frame", help="State phase 1: object (also see the scene from the block's frame) or world (world coordinates only)."),
    feedback: Optional[str] = typer.Option(None, "--feedback", help="Image phase 2: frames fed back as context, denoised (one-step estimate, default) or sampled."),
    options: dict | None = None,
) -> None:
    """Train a world model (phase 1, then phase 2 from it); checkpoints land in OUT/checkpoints."""
    from models.world_model_config import FEEDBACK, OBS_TYPES, world_model_profile
    from models.world_model_training import find_phase_one, train_world_model

    if obs not in OBS_TYPES:
        raise typer.BadParameter(f"world model obs {obs!r}: use one of {', '.join(OBS_TYPES)}", param_hint="--obs")
    if unroll is not None and phase != 2:
        raise typer.BadParameter("--unroll applies to phase 2", param_hint="--unroll")
    if feedback is not None and (obs != "image" or phase != 2 or feedback not in FEEDBACK):
        raise typer.BadParameter(f"--feedback applies to --obs image --phase 2 and is one of {', '.join(FEEDBACK)}",
                                 param_hint="--feedback")
    try:
        chosen = world_model_profile(profile, phase, task, obs, frame)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--frame" if "frame" in str(exc) else "--profile") from None
    config = dataclasses.replace(chosen.config, unroll=unroll, **({"feedback": feedback} if feedback else {}))
    if phase == 2 and init is None and not options["resume"]:
        init = find_phase_one(out)
        typer.echo(f"phase 2 starts from {init}")
    run = run_config(out, chosen.max_steps, chosen.batch_size, task=task, **options)
    echo_result(train_world_model(config, dataset, run, init=init))


@world_model_app.command("eval")
def evaluate(
    checkpoint: Path = typer.Argument(..., help="World model checkpoint (its config and normaliser are inside)."),
    dataset: List[Path] = typer.Option(..., "--dataset", "-d", help="Zarr episode store(s); with --split val, the stores it was trained on."),
    split: str = typer.Option("val", "--split", help="val: the held-out episodes of the training split; all: every episode."),
    episodes: Optional[int] = typer.Option(None, "--episodes", "-n", min=1, help="Only the first N of those episodes."),
    horizon: Optional[int] = typer.Option(None, "--horizon", min=1, help="Actions rolled out per window (default: the training horizon)."),
    stride: Optional[int] = typer.Option(None, "--stride", min=1, help="Steps between window starts (default: 1 for state, 8 for image models)."),
    max_windows: int = typer.Option(512, "--max-windows", min=1, help="Image models: at most this many windows, evenly spread."),
    noise: str = typer.Option("frozen", "--noise", help="Image models: frozen (deterministic) or sampled initial noise."),
    sampler_steps: Optional[int] = typer.Option(None, "--sampler-steps", min=1, help="Image models: Euler steps per predicted frame (default: the checkpoint's, 3)."),
    pose_reader: Optional[Path] = typer.Option(None, "--pose-reader", help="Image models: read the block pose with this `gpc train reward` checkpoint (what the learned reward sees) instead of by colour."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Directory for world_model_eval.json and .md (default: the run's eval/)."),
) -> None:
    """Open-loop rollout errors per horizon step on held-out windows, beside the nothing-moves baseline.

    Image models: SSIM and PSNR per predicted frame, the block pose read from the frames by
    colour against the recorded frames' (on windows where the block moves), the share of
    predicted frames where the agent is visible, and a PNG grid of recorded over predicted frames.
    """
    from models.world_model import WorldModelModule
    from models.world_model_config import VisualWorldModelConfig
    from models.world_model_eval import evaluate_rollouts, markdown_table
    from tasks import get_task

    module = WorldModelModule.load_from_checkpoint(checkpoint)
    if out is None:
        out = checkpoint.parent.parent / "eval" if checkpoint.parent.name == "checkpoints" else checkpoint.parent / "eval"
    if isinstance(module.config, VisualWorldModelConfig):
        import cv2

        from models.edm import NOISE_MODES
        from models.visual_world_model_eval import evaluate_visual_rollouts, visual_markdown_table

        if noise not in NOISE_MODES:
            raise typer.BadParameter(f"noise {noise!r}: use one of {', '.join(NOISE_MODES)}", param_hint="--noise")
        if sampler_steps is not None:
            module.dynamics.use_sampler(dataclasses.replace(module.dynamics.config.sampler, steps=sampler_steps))
        readout = frame_readout(module.config.task)
        if pose_reader is not None:
            from models.reward_predictor import RewardPredictorModule
            from models.visual_world_model_eval import LearnedPoseReadout

            predictor = RewardPredictorModule.load_from_checkpoint(pose_reader, task=module.config.task).predictor
            readout = LearnedPoseReadout(readout, predictor, str(pose_reader))
        report, grid = evaluate_visual_rollouts(module, dataset, split=split, episodes=episodes, horizon=horizon,
                                                readout=readout, stride=stride or 8,
                                                max_windows=max_windows, noise=noise)
        table = visual_markdown_table(report, f"Visual world model rollouts: {checkpoint}")
        out.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / "world_model_frames.png"), grid[..., ::-1])
        extra = f", {out / 'world_model_frames.png'}"
    else:
        for value, hint in ((pose_reader, "--pose-reader"), (sampler_steps, "--sampler-steps")):
            if value is not None:
                raise typer.BadParameter("applies to image world models only", param_hint=hint)
        geometry = get_task(module.config.task).geometry
        report = evaluate_rollouts(module, dataset, split=split, episodes=episodes, horizon=horizon,
                                   vertices=geometry.TEE_BOXES.reshape(-1, 2), stride=stride or 1)
        table, extra = markdown_table(report, f"World model rollouts: {checkpoint}"), ""
    report["checkpoint"] = str(checkpoint)
    out.mkdir(parents=True, exist_ok=True)
    (out / "world_model_eval.json").write_text(json.dumps(report, indent=2))
    (out / "world_model_eval.md").write_text(table)
    typer.echo(table + f"\nwrote {out / 'world_model_eval.json'}, {out / 'world_model_eval.md'}{extra}")


def frame_readout(task: str):
    """The colour readout of a task's rendered frames (Push-T: the T block's colours and axis, the agent's colours)."""
    from models.visual_world_model_eval import ColourReadout

    if task != "pusht":
        raise typer.BadParameter(f"no frame readout for task {task!r}", param_hint="--task")
    from tasks.pusht import geometry, render

    # The T's stem runs along its body +y axis, its principal axis: body angle = axis angle - pi / 2.
    return ColourReadout(object_colours=(render.BLOCK_FILL, render.BLOCK_EDGE),
                         agent_colours=(render.AGENT_FILL, render.AGENT_EDGE),
                         angle_offset=-math.pi / 2, extent=float(geometry.WORKSPACE),
                         vertices=tuple((float(x), float(y)) for x, y in geometry.TEE_BOXES.reshape(-1, 2)),
                         centroid=(float(geometry.TEE_CENTROID[0]), float(geometry.TEE_CENTROID[1])))


if __name__ == "__main__":  # `python -m gpc_cli.world_model train ...` (DDP re-launches this way)
    world_model_app()
