"""What a gpc checkpoint says about itself, and reading one with clear errors.

Every LightningModule of this library adds ``checkpoint["gpc"] = {"format", "kind", "task",
...}`` on save (kind: ``policy``, ``world_model``, ...). ``read_checkpoint`` refuses files
that are missing, unreadable, not ours, or of another kind, task or observation type, with
one ``DataError`` naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from gpc.datasets.errors import DataError

FORMAT = 1
META_KEY = "gpc"


def checkpoint_meta(kind: str, task: str, **extra: Any) -> dict[str, Any]:
    return {"format": FORMAT, "kind": kind, "task": task, **extra}


def read_checkpoint(
    path: str | os.PathLike, kind: str, task: str | None = None, map_location: Any = "cpu", **expect: Any
) -> dict[str, Any]:
    """Load a checkpoint dict (tensors and plain data only) after checking its record.

    ``expect`` names further record fields to match (e.g. ``obs="state"``); ``None`` skips one.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises many types for truncated or foreign files
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise DataError(f"{path}: unreadable or corrupt checkpoint ({type(exc).__name__}: {first[:200]})") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get(META_KEY), dict):
        raise DataError(f"{path}: not a gpc checkpoint (no '{META_KEY}' record)")
    meta = ckpt[META_KEY]
    if meta.get("kind") != kind:
        raise DataError(f"{path}: is a {meta.get('kind')!r} checkpoint, expected a {kind!r} checkpoint")
    if meta.get("format", 0) > FORMAT:
        raise DataError(f"{path}: checkpoint format {meta.get('format')} is newer than this gpc ({FORMAT})")
    if task is not None and meta.get("task") != task:
        raise DataError(f"{path}: {kind} checkpoint for task {meta.get('task')!r}, expected task {task!r}")
    for key, want in expect.items():
        if want is not None and meta.get(key) != want:
            raise DataError(f"{path}: {kind} checkpoint has {key} {meta.get(key)!r}, expected {want!r}")
    return ckpt


def rebuild(cls: Any, ckpt: dict[str, Any], path: str | os.PathLike, what: str) -> Any:
    """The module a checked checkpoint describes: its saved config (and data record), then its weights, in eval mode.

    A checkpoint whose weights or config this gpc cannot take raises one ``ValueError`` naming the file.
    """
    try:
        hp = ckpt["hyper_parameters"]
        module = cls(hp["config"], **({"data": hp["data"]} if "data" in hp else {}))
        module.load_state_dict(ckpt["state_dict"])
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path}: {what} checkpoint does not match this gpc's {what} ({first[:200]})") from None
    return module.eval()
