"""One entry point for every policy gpc plans with: its own checkpoints, LeRobot's and Diffusion Policy's.

``load_policy(path)`` detects the format (or takes ``format``) and returns a ``PolicyModule``:
a gpc checkpoint as it is, a foreign one converted once into gpc's own Diffusion Policy (the
same network, renamed; see ``common``), whose observations the task provides under its own
keys (``Task.foreign_features``). ``module.source`` records where it came from.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from gpc.datasets.errors import DataError
from gpc.models.policy.formats.common import FeatureSource, build
from gpc.models.policy.module import PolicyModule

GPC, LEROBOT, DIFFUSION_POLICY = "gpc", "lerobot", "diffusion_policy"
FORMATS = (GPC, LEROBOT, DIFFUSION_POLICY)
PRETRAINED = "pretrained_model"  # where lerobot-train puts the policy inside a checkpoint folder


class ForeignTask(Protocol):
    """What a task tells the loader (``gpc.tasks.base.Task`` is one): its name, where it has other
    frameworks' observation features, and the shape of its keys."""

    @property
    def name(self) -> str: ...

    @property
    def foreign_features(self) -> Mapping[str, tuple[str, int | None]]: ...

    def row_shape(self, key: str) -> tuple[int, ...] | None: ...


def feature_sources(task: ForeignTask) -> dict[str, FeatureSource]:
    """The task's sources of other frameworks' observation features, with the shapes of its keys."""
    return {name: FeatureSource(key, task.row_shape(key), take) for name, (key, take) in task.foreign_features.items()}


def detect_format(path: str | os.PathLike) -> str:
    """``lerobot`` for a directory with ``config.json`` (or its ``pretrained_model/``), else ``gpc`` or
    ``diffusion_policy`` for a torch checkpoint, told apart by what its pickle holds."""
    p = Path(path)
    if p.is_dir():
        if (p / "config.json").is_file() or (p / PRETRAINED / "config.json").is_file():
            return LEROBOT
        raise DataError(f"{p}: a directory without config.json (a LeRobot policy directory has config.json and model.safetensors)")
    if not p.is_file():
        raise DataError(f"{p}: no such checkpoint file or policy directory")
    if p.name in ("config.json", "model.safetensors"):
        return LEROBOT
    try:
        with zipfile.ZipFile(p) as archive:
            pickled = next((n for n in archive.namelist() if n.endswith("data.pkl")), None)
            data = archive.read(pickled) if pickled else b""
    except (zipfile.BadZipFile, OSError):
        raise DataError(f"{p}: not a policy checkpoint (neither a torch checkpoint nor a LeRobot directory)") from None
    return DIFFUSION_POLICY if b"state_dicts" in data and b"pickles" in data else GPC


def _lerobot_dir(path: Path) -> Path:
    if path.is_file():
        return path.parent
    return path / PRETRAINED if not (path / "config.json").is_file() and (path / PRETRAINED).is_dir() else path


def load_policy(path: str | os.PathLike, sources: Mapping[str, FeatureSource] | None = None, task: str | None = None,
                format: str | None = None, map_location: Any = "cpu") -> PolicyModule:
    """The policy at ``path``: a gpc checkpoint (checked against ``task`` when given), a LeRobot directory or a
    Diffusion Policy ``.ckpt`` (both need ``task`` and its ``sources``: ``gpc.harness.policies`` fills them)."""
    kind = format or detect_format(path)
    if kind not in FORMATS:
        raise ValueError(f"--policy-format {kind!r}: use one of {', '.join(FORMATS)}")
    p = Path(path)
    if kind == GPC:
        module = PolicyModule.load_from_checkpoint(p, map_location=map_location, task=task)
        module.source = {"path": str(p), "format": GPC}
        return module
    if task is None or sources is None:
        raise ValueError(f"{p}: a {kind} policy needs the task it acts in (--task) to map its observations")
    if kind == LEROBOT:
        from gpc.models.policy.formats import lerobot

        directory = _lerobot_dir(p)
        if not lerobot.is_lerobot(directory):
            raise DataError(f"{directory}: no config.json (not a LeRobot policy directory)")
        return build(lerobot.load(directory, sources, task), str(directory))
    from gpc.models.policy.formats import diffusion_policy

    if p.is_dir() or not p.exists():
        raise DataError(f"{p}: not a Diffusion Policy .ckpt file")
    return build(diffusion_policy.load(p, sources, task), str(p))


__all__ = ["FORMATS", "FeatureSource", "ForeignTask", "detect_format", "feature_sources", "load_policy"]
