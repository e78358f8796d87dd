"""Open-loop evaluations of trained components, from a checkpoint to files on disk.

``evaluate_world_model`` scores a world model's rollouts on held-out windows (state models:
per-step pose errors; visual models: SSIM, PSNR, the object pose read by colour or by a
learned reader, agent visibility, and a PNG grid), ``evaluate_reward`` a learned image
reward's registration loss against the true one. Each writes JSON and Markdown and returns
the Markdown and the files it wrote. The task's layout supplies poses and colours.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError
from gpc.datasets.locks import exclusive
from gpc.datasets.sequence import HeldOutOf
from gpc.harness import interrupts
from gpc.harness.files import check_out, write_atomic, write_bytes_atomic
from gpc.harness.ownership import claim
from gpc.tasks import get_task

STATE_STRIDE, IMAGE_STRIDE = 1, 8  # default steps between window starts
WORLD_MODEL_FILES = ("world_model_eval.json", "world_model_eval.md", "world_model_frames.png")
REWARD_FILES = ("reward_eval.json", "reward_eval.md")


@dataclass(frozen=True)
class Written:
    """What an evaluation printed and where its files are."""

    markdown: str
    files: tuple[Path, ...]


def default_out(checkpoint: Path) -> Path:
    """``RUN/eval`` for ``RUN/checkpoints/X.ckpt``, else ``eval`` beside the checkpoint."""
    return checkpoint.parent.parent / "eval" if checkpoint.parent.name == "checkpoints" else checkpoint.parent / "eval"


def evaluate_world_model(checkpoint: Path, datasets: Sequence[Path], out: Path | None = None, split: str = "val",
                         episodes: int | None = None, horizon: int | None = None, stride: int | None = None,
                         max_windows: int = 512, noise: str = "frozen", sampler_steps: int | None = None,
                         pose_reader: Path | None = None, held_out_of: Path | None = None) -> Written:
    """Rollout errors per horizon step beside the nothing-moves baseline; ``out``: default ``default_out``.

    ``max_windows``, ``noise``, ``sampler_steps`` and ``pose_reader`` apply to visual models only;
    ``held_out_of``: a checkpoint whose held-out episodes to use instead of this one's (two models, one test set).
    """
    out = out or default_out(checkpoint)
    check_out(out)
    claim([out / name for name in WORLD_MODEL_FILES])
    other = _held_out_of(held_out_of)
    with exclusive(out, "evaluation folder"):
        return _world_model(checkpoint, datasets, out, split, episodes, horizon, stride, max_windows, noise,
                            sampler_steps, pose_reader, other)


def _held_out_of(path: Path | None) -> HeldOutOf | None:
    if path is None:
        return None
    from gpc.models.training.checkpoint import read_checkpoint

    record = read_checkpoint(path, None).get("hyper_parameters", {}).get("data")
    if not record:
        raise DataError(f"{path}: records no training data to take held-out episodes from")
    return HeldOutOf(str(path), dict(record))


def _world_model(checkpoint: Path, datasets: Sequence[Path], out: Path, split: str, episodes: int | None,
                 horizon: int | None, stride: int | None, max_windows: int, noise: str, sampler_steps: int | None,
                 pose_reader: Path | None, held_out_of: HeldOutOf | None) -> Written:
    from gpc.models.world_models.config import VisualWorldModelConfig
    from gpc.models.world_models.ensemble import WorldModelEnsemble, load_any

    module: Any = load_any(checkpoint)
    layout = get_task(module.config.task).layout
    files: list[Path] = []
    if isinstance(module.config, VisualWorldModelConfig):
        if isinstance(module, WorldModelEnsemble):
            raise ValueError(f"{checkpoint}: an ensemble of visual world models; judge its members one by one")
        import cv2

        from gpc.models.networks.edm import NOISE_MODES
        from gpc.models.world_models.eval_visual import (
            ColourReadout,
            LearnedPoseReadout,
            evaluate_visual_rollouts,
            visual_markdown_table,
        )

        if noise not in NOISE_MODES:
            raise ValueError(f"--noise {noise!r}: use one of {', '.join(NOISE_MODES)}")
        if sampler_steps is not None:
            module.dynamics.use_sampler(dataclasses.replace(module.dynamics.config.sampler, steps=sampler_steps))
        from gpc.models.world_models.regions import RegionReadout

        regions = RegionReadout.from_layout(layout)
        # Objects are read by colour where the task names how they are drawn; a drawing's ink is a region, and a
        # perspective camera's shaded boxes (Block Stacking) have no planar colour readout: image figures only.
        frame = layout.frame
        colour = ColourReadout.from_layout(layout) if frame is not None and frame.objects and frame.agent_colours else None
        readout: ColourReadout | LearnedPoseReadout | None = colour
        state_readout = None
        if pose_reader is not None:
            from gpc.models.rewards.learned import RewardPredictorModule, StatePredictor

            predictor = RewardPredictorModule.load_from_checkpoint(pose_reader, task=module.config.task).predictor
            if isinstance(predictor, StatePredictor):  # reads the whole state: judged on every object's position (and height)
                from gpc.models.world_models.state_readout import StateReadout

                state_readout = StateReadout(predictor, layout, str(pose_reader))
            elif colour is None:
                raise ValueError(f"--pose-reader {pose_reader}: a pose predictor, and task {layout.name}'s frames name no "
                                 "object colours to read the agent beside it (a state reader, trained for a task scored by "
                                 "its own state reward, reads any task)")
            else:
                readout = LearnedPoseReadout(colour, predictor, str(pose_reader))
        report, grid = evaluate_visual_rollouts(module, datasets, split=split, episodes=episodes, horizon=horizon,
                                                readout=readout, stride=stride or IMAGE_STRIDE,
                                                max_windows=max_windows, noise=noise, held_out_of=held_out_of, regions=regions,
                                                state_readout=state_readout)
        table = visual_markdown_table(report, f"Visual world model rollouts: {checkpoint}")
        interrupts.check()
        out.mkdir(parents=True, exist_ok=True)
        ok, png = cv2.imencode(".png", grid[..., ::-1])
        if not ok:
            raise DataError(f"{out / 'world_model_frames.png'}: OpenCV could not encode the grid")
        write_bytes_atomic(out / "world_model_frames.png", png.tobytes())
        files.append(out / "world_model_frames.png")
    else:
        from gpc.models.world_models.eval_state import evaluate_rollouts, markdown_table

        for value, option in ((pose_reader, "--pose-reader"), (sampler_steps, "--sampler-steps")):
            if value is not None:
                raise ValueError(f"{option} applies to image world models only")
        from gpc.models.rewards.registration import RewardConfig
        from gpc.models.rewards.state import state_reward

        task = get_task(module.config.task)
        # the task's planning reward, judged on each predicted state; registration against a goal drawn per episode
        # would need the stores' goals, so that reward is left out there
        per_episode_goal = task.state_reward == "registration" and layout.goal is None
        reward = None if per_episode_goal else state_reward(task.state_reward, layout, RewardConfig(aggregate="final"))
        report = evaluate_rollouts(module, datasets, split=split, episodes=episodes, horizon=horizon, layout=layout,
                                   stride=stride or STATE_STRIDE, held_out_of=held_out_of, reward=reward)
        table = markdown_table(report, f"World model rollouts: {checkpoint}")
    report["checkpoint"] = str(checkpoint)
    if isinstance(module, WorldModelEnsemble):  # its mean prediction is judged; the config is its first member's
        report["ensemble"] = module.summary()
    interrupts.check()
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "world_model_eval.json", json.dumps(report, indent=2))
    write_atomic(out / "world_model_eval.md", table)
    return Written(table, (out / "world_model_eval.json", out / "world_model_eval.md", *files))


def evaluate_reward(checkpoint: Path, datasets: Sequence[Path], out: Path | None = None, split: str = "val",
                    ood: Sequence[Path] = (), episodes: int | None = None, stride: int = 1,
                    image_size: int | None = None) -> Written:
    """Predicted vs true registration loss on the held-out frames of ``datasets`` and on every frame of each ``ood`` store."""
    from gpc.models.rewards.learned import RewardPredictorModule
    from gpc.models.rewards.learned_eval import evaluate_reward_predictor, evaluate_state_reader, markdown_report, state_reader_report
    from gpc.models.rewards.state import state_reward

    out = out or default_out(checkpoint)
    check_out(out)
    claim([out / name for name in REWARD_FILES])
    with exclusive(out, "evaluation folder"):
        module = RewardPredictorModule.load_from_checkpoint(checkpoint)
        reader = module.config.state_reward  # a state reader: scored by the task's own state reward
        reward = state_reward(reader, get_task(module.config.task).layout) if reader else None
        sets = [(list(datasets), split)] + [([p], "all") for p in ood]
        reports = []
        for paths, which in sets:
            if reward is not None:
                report = evaluate_state_reader(module, paths, reward, split=which, episodes=episodes, stride=stride,
                                               frame_size=image_size)
            else:
                report = evaluate_reward_predictor(module, paths, split=which, episodes=episodes, stride=stride,
                                                   frame_size=image_size)
            report["checkpoint"] = str(checkpoint)
            reports.append(report)
            interrupts.check()
        out.mkdir(parents=True, exist_ok=True)
        table = (state_reader_report if reward is not None else markdown_report)(reports, f"Image reward: {checkpoint}")
        write_atomic(out / "reward_eval.json", json.dumps(reports, indent=2))
        write_atomic(out / "reward_eval.md", table)
    return Written(table, (out / "reward_eval.json", out / "reward_eval.md"))
