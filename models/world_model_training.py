"""One world-model training run (phase 1 or 2) through the shared loop of ``models.training``.

Same run directory layout, resume and NaN handling as the policy's, for state and visual
world models alike. Phase 2 starts from a phase-1 checkpoint (``init``): its network config,
held-out episodes, normaliser and weights are taken as they are, with a fresh optimiser and
phase 2's own schedule. ``find_phase_one`` finds that checkpoint beside a phase-2 run directory.

A visual model records the frame size of its training stores (``source_size``); a store of
another size is resized to the model's resolution with a warning.
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

import lightning as L
from lightning.pytorch.utilities import rank_zero_only

from datasets.datamodule import DataConfig, EpisodeDataModule
from datasets.errors import DataError
from datasets.normalizer import MinMaxNormalizer
from datasets.sequence import recorded_split
from models.checkpoint import read_checkpoint
from models.training import LAST, RunConfig, TrainResult, check_run_dir, fit_module
from models.world_model import ACTION_KEY, DELTA_KEY, STATE_KEY, WorldModelModule, delta_statistics
from models.world_model_config import KIND, AnyWorldModelConfig, VisualWorldModelConfig, config_from_dict, with_network_of

_PHASE_TAGS = (("phase2", "phase1"), ("phase-2", "phase-1"), ("phase_2", "phase_1"))


def world_model_data_config(config: AnyWorldModelConfig, datasets: Sequence[str | os.PathLike], run: RunConfig,
                            split: tuple[int, float] | None = None) -> DataConfig:
    """Windows of the history and T futures (observations and actions); histories padded at
    episode starts, futures never padded. ``split``: (seed, val ratio) of the held-out episodes
    (default: the run's)."""
    h = config.n_obs_steps
    split_seed, val_ratio = split if split is not None else (run.seed, run.val_ratio)
    return DataConfig(
        paths=tuple(str(p) for p in datasets), obs_keys=(config.obs_key,), action_key=ACTION_KEY, horizon=config.window,
        n_obs_steps=h, n_action_steps=1, obs_steps_override=config.window, val_ratio=val_ratio, seed=split_seed,
        batch_size=run.batch_size, num_workers=run.num_workers,
    )


def find_phase_one(out: str | os.PathLike) -> Path:
    """``last.ckpt`` of the phase-1 run beside the phase-2 run directory ``out``.

    ``runs/wm-phase2`` looks in ``runs/wm-phase1`` (also ``phase-2``/``phase_2``); any other
    name ``NAME`` looks in ``NAME-phase1``.
    """
    out = Path(out)
    names = [out.name.replace(a, b) for a, b in _PHASE_TAGS if a in out.name] + [f"{out.name}-phase1"]
    candidates = [out.with_name(n) / "checkpoints" / LAST for n in dict.fromkeys(names)]
    for path in candidates:
        if path.is_file():
            return path
    raise DataError(
        f"phase 2 starts from phase-1 weights and found none (looked for {', '.join(map(str, candidates))}); "
        "pass --init PHASE1_RUN/checkpoints/last.ckpt"
    )


def _stored_config(ckpt: dict[str, Any], path: Path) -> AnyWorldModelConfig:
    try:
        return config_from_dict(ckpt["hyper_parameters"]["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: world model checkpoint with an unreadable config ({exc})") from None


@rank_zero_only
def _write_run_record(run_dir: Path, config: AnyWorldModelConfig, record: dict[str, Any], run: RunConfig) -> None:
    out = {"kind": KIND, "world_model": config.to_dict(), **record,
           "run": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()}}
    (run_dir / "run.json").write_text(json.dumps(out, indent=2))


def check_observations(config: AnyWorldModelConfig, arrays: Any, source: str | os.PathLike) -> AnyWorldModelConfig:
    """Refuse stores whose observations or actions do not fit ``config``; a visual config gets the
    stores' frame size as ``source_size`` (a size other than a recorded one is resized, with a warning)."""
    dyn = config.dynamics
    actions = tuple(arrays.data[ACTION_KEY].shape[1:])
    if actions != (dyn.action_dim,):
        raise DataError(f"{source}: data/{ACTION_KEY} rows are {actions}, the world model needs ({dyn.action_dim},)")
    shape = tuple(arrays.data[config.obs_key].shape[1:])
    if not isinstance(config, VisualWorldModelConfig):
        if shape != (dyn.state_dim,):
            raise DataError(f"{source}: data/{config.obs_key} rows are {shape}, the world model needs ({dyn.state_dim},)")
        return config
    if len(shape) != 3 or shape[0] != shape[1] or shape[2] != dyn.img_channels:
        raise DataError(f"{source}: data/{config.obs_key} frames are {shape}; the visual world model needs square "
                        f"(S, S, {dyn.img_channels}) RGB frames")
    if dyn.source_size is not None and dyn.source_size != shape[0]:
        warnings.warn(f"{source}: frames are {shape[0]} px, the model's earlier training used {dyn.source_size} px; "
                      f"resizing {shape[0]} -> {dyn.resolution} px", stacklevel=2)
        return config
    return dataclasses.replace(config, dynamics=dataclasses.replace(dyn, source_size=shape[0]))


def train_world_model(config: AnyWorldModelConfig, datasets: Sequence[str | os.PathLike], run: RunConfig,
                      init: str | os.PathLike | None = None) -> TrainResult:
    """Train (or resume) a state or visual world model; phase 2 needs ``init`` (a phase-1 checkpoint) unless resuming."""
    run_dir = Path(run.run_dir)
    last = check_run_dir(run)
    start_step, init_state, ckpt = 0, None, None
    if run.resume:
        ckpt = read_checkpoint(last, KIND, task=config.task, obs=config.obs_type)
        stored = _stored_config(ckpt, last)
        if stored.phase != config.phase:
            raise DataError(f"{last}: the run in {run_dir} is phase {stored.phase}, not phase {config.phase}")
        config, start_step = stored, int(ckpt.get("global_step", 0))
        init = ckpt["hyper_parameters"].get("data", {}).get("init")
    elif init is not None:
        ckpt = read_checkpoint(init, KIND, task=config.task, obs=config.obs_type)
        config = with_network_of(config, _stored_config(ckpt, Path(init)))
        init_state = {k[len("dynamics."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("dynamics.")}
    elif config.phase == 2:
        raise DataError("phase 2 starts from phase-1 weights: pass init (--init PHASE1_RUN/checkpoints/last.ckpt)")

    # A run started from a checkpoint holds out the episodes it held out, whatever its own seed:
    # otherwise its "held-out" episodes would have been trained on.
    split = (recorded_split(ckpt["hyper_parameters"].get("data", {})) if ckpt else None) or (run.seed, run.val_ratio)
    data = EpisodeDataModule(world_model_data_config(config, datasets, run, split))
    config = check_observations(config, data.arrays, datasets[0])
    record = {"datasets": [str(p) for p in datasets], "val_ratio": split[1], "seed": run.seed, "split_seed": split[0],
              "init": None if init is None else str(init)}
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    _write_run_record(run_dir, config, record, run)

    L.seed_everything(run.seed + start_step, workers=True, verbose=False)
    if init_state is None:
        normalizer = data.normalizer
        if not isinstance(config, VisualWorldModelConfig):
            lo, hi = delta_statistics(data.arrays.data[STATE_KEY], data.arrays.episode_ends, data.train_episodes,
                                      config.dynamics.angle_dims)
            normalizer.add(DELTA_KEY, lo, hi)
        module = WorldModelModule(config, normalizer=normalizer, data=record)
    else:
        module = WorldModelModule(config, normalizer=MinMaxNormalizer(), data=record)
        try:
            module.dynamics.load_state_dict(init_state)
        except RuntimeError as exc:
            raise DataError(f"{init}: weights do not fit the world model ({str(exc).splitlines()[0][:200]})") from None
    return fit_module(module, data, run, validate=len(data.val_episodes) > 0)
