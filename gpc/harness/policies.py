"""Policies from any supported file for a task: gpc checkpoints, LeRobot directories, Diffusion Policy ``.ckpt``.

Here the task joins the loader (``gpc.models.policy.formats``): a foreign policy names its
observations in its own framework's terms, and the task says where it has each one
(``Task.foreign_features``) and how large that is (``Task.row_shape``).
"""

from __future__ import annotations

import os
from typing import Any

from gpc.models.policy.formats import GPC, detect_format, feature_sources
from gpc.models.policy.formats import load_policy as load_any
from gpc.models.policy.module import PolicyModule
from gpc.tasks import DEFAULT_TASK, get_task


def load_policy(path: str | os.PathLike, task: str | None = None, format: str | None = None, map_location: Any = "cpu") -> PolicyModule:
    """The policy at ``path`` as a ``PolicyModule``; a foreign one acts in ``task`` (default: the built-in task)."""
    kind = format or detect_format(path)
    if kind == GPC:
        return load_any(path, task=task, format=kind, map_location=map_location)
    chosen = get_task(task or DEFAULT_TASK)
    return load_any(path, feature_sources(chosen), chosen.name, kind, map_location)


def describe(policy: PolicyModule) -> dict[str, Any]:
    """What ``gpc inspect`` prints: format, observations, horizons, sampler, size, normaliser ranges."""
    import torch

    cfg = policy.config
    ranges = {}
    for key in policy.normalizer.keys():
        ends = torch.tensor([-1.0, 1.0]).reshape((2,) + (1,) * policy.normalizer.scales[key].dim())
        lo, hi = policy.normalizer.unnormalize(key, ends)
        ranges[key] = {"low": [round(float(v), 4) for v in lo.reshape(-1)[:8]],
                       "high": [round(float(v), 4) for v in hi.reshape(-1)[:8]], "size": int(lo.numel())}
    return {
        **policy.source, "task": cfg.task,
        "observations": {key: list(cfg.encoder.shape(key)) for key in policy.obs_keys}, "obs_type": cfg.obs_type,
        "action_dim": cfg.action_dim, "horizon": cfg.horizon, "n_obs_steps": cfg.n_obs_steps,
        "n_action_steps": cfg.n_action_steps,
        "executed": f"actions {policy.action_slice.start}..{policy.action_slice.stop - 1} of each chunk",
        "noise": {"train_steps": cfg.noise.train_steps, "beta_schedule": cfg.noise.beta_schedule, "prediction": cfg.noise.prediction,
                  "clip_sample": cfg.noise.clip_sample},
        "sampler": {"method": cfg.sampler.method, "steps": cfg.sampler.steps, "spacing": cfg.sampler.spacing},
        "parameters": sum(p.numel() for p in policy.model.parameters()),
        "normalizer_ranges": ranges,
    }
