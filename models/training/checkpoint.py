"""What a gpc checkpoint says about itself, and reading one with clear errors.

Every LightningModule of this library adds ``checkpoint["gpc"] = {"format", "kind", "task",
...}`` on save (kind: ``policy``, ``world_model``, ...). ``read_checkpoint`` refuses files
that are missing, unreadable, not ours, or of another kind, task or observation type, with
one ``DataError`` naming the file. ``for_planning`` is what `gpc export` writes: what planning reads of a
training checkpoint, a quarter of its size for the policy.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from gpc.datasets.errors import DataError

FORMAT = 1
META_KEY = "gpc"
AVERAGED = "ema.model."  # where a module's averaged copy of its network sits in its state dict
RAW_FROM_AVERAGE = "raw_from_average"  # record field of an export: the network's prefix, refilled from the average
HALF = "half"  # record field of an export whose network weights are stored in float16
NORMALISER = "normalizer."  # where a module's normaliser sits in its state dict: never rounded


def checkpoint_meta(kind: str, task: str, **extra: Any) -> dict[str, Any]:
    return {"format": FORMAT, "kind": kind, "task": task, **extra}


def read_checkpoint(
    path: str | os.PathLike, kind: str | None, task: str | None = None, map_location: Any = "cpu", **expect: Any
) -> dict[str, Any]:
    """Load a checkpoint dict (tensors and plain data only) after checking its record.

    ``kind``: None takes any kind; ``expect`` names further record fields to match (e.g. ``obs="state"``); ``None`` skips one.
    """
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not a checkpoint file")
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
    if kind is not None and meta.get("kind") != kind:
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
        module.load_state_dict(module_state(ckpt))
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path}: {what} checkpoint does not match this gpc's {what} ({first[:200]})") from None
    return module.eval()


def for_planning(ckpt: dict[str, Any], half: bool = False) -> dict[str, Any]:
    """A checked checkpoint without what only training reads (optimiser state, loops, callbacks).

    Where the module keeps an averaged copy of its network (the policy samples with it), the raw copy is dropped
    as well and ``module_state`` refills it from the average on load: planning gives the same actions, and
    training can start from it (``--init``) but not resume it. ``half``: the network's weights stored in float16,
    half the file; loading casts them back to float32, so the model plans with rounded weights (figures are
    measured with the exported file, not the trained one).
    """
    state = ckpt["state_dict"]
    meta = dict(ckpt[META_KEY])
    averaged = [k[len(AVERAGED):] for k in state if k.startswith(AVERAGED)]
    prefix = _raw_prefix(state, averaged) if averaged else None
    if prefix is not None:
        raw = {prefix + k for k in averaged}
        state = {k: v for k, v in state.items() if k not in raw}
        meta[RAW_FROM_AVERAGE] = prefix
    if half:
        state = {k: _half(k, v) for k, v in state.items()}
        meta[HALF] = True
    return {META_KEY: meta, "hyper_parameters": ckpt["hyper_parameters"], "state_dict": state}


def _half(key: str, value: torch.Tensor) -> torch.Tensor:
    """float16 for a network weight; the normaliser (the data's units), integers and values float16 cannot hold stay
    as trained."""
    if not value.is_floating_point() or NORMALISER in key:
        return value
    fits = not value.numel() or bool(value.abs().max() <= torch.finfo(torch.float16).max)
    return value.to(torch.float16) if fits else value


def module_state(ckpt: dict[str, Any]) -> dict[str, Any]:
    """The state dict the module loads: an export's raw network refilled from its average."""
    state = ckpt["state_dict"]
    prefix = ckpt.get(META_KEY, {}).get(RAW_FROM_AVERAGE)
    if prefix is None:
        return state
    return {**state, **{prefix + k[len(AVERAGED):]: v for k, v in state.items() if k.startswith(AVERAGED)}}


def _raw_prefix(state: dict[str, Any], averaged: list[str]) -> str | None:
    """The prefix under which every averaged entry also sits as the raw network (``model.`` for the policy)."""
    first = averaged[0]
    candidates = {k[: len(k) - len(first)] for k in state
                  if k.endswith("." + first) and not k.startswith(AVERAGED)}
    found = [p for p in candidates if all(p + k in state for k in averaged)]
    return found[0] if len(found) == 1 else None
