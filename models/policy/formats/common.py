"""What every foreign checkpoint becomes: a gpc ``PolicyModule`` plus a record of where it came from.

A loader (LeRobot, Diffusion Policy) reads its files and returns an ``Imported``: the gpc
config, the normaliser (other frameworks' statistics folded into per-feature affine maps,
exactly), and the weights under gpc's names. ``build`` makes the module from it, so a policy
trained elsewhere plans and evaluates through the same code as one trained here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.policy.config import PolicyConfig
from gpc.models.policy.formats.weights import load_exact
from gpc.models.policy.module import PolicyModule

IMAGE_RANGE = 255.0  # tasks store images as uint8; other frameworks feed them as floats in [0, 1]


@dataclass(frozen=True)
class FeatureSource:
    """Where a task has another framework's observation feature."""

    key: str  # the task's observation key
    shape: tuple[int, ...] | None  # one step of that key (None: not fixed, e.g. images)
    take: int | None = None  # the feature is this many leading entries of the key (None: all of it)

    @property
    def width(self) -> int | None:
        if self.take is not None:
            return self.take
        return None if self.shape is None else int(np.prod(self.shape))


@dataclass
class Imported:
    """A foreign checkpoint in gpc's terms."""

    config: PolicyConfig
    normalizer: MinMaxNormalizer
    weights: dict[str, torch.Tensor]  # the network (ActionDenoiser) under gpc's names
    ema_weights: dict[str, torch.Tensor] | None = None  # the averaged copy, when the run kept one
    source: dict[str, Any] = field(default_factory=dict)  # what `gpc inspect` reports: format, files, features


def build(imported: Imported, path: str) -> PolicyModule:
    """The PolicyModule an ``Imported`` describes, in eval mode, with ``source`` recorded on it."""
    module = PolicyModule(imported.config, normalizer=imported.normalizer)
    load_exact(module.model, imported.weights, path)
    if module.ema is not None:
        load_exact(module.ema.model, imported.ema_weights or imported.weights, path)
    module.source = {"path": path, **imported.source}
    return module.eval()


def source_for(sources: Mapping[str, FeatureSource], name: str, path: str, task: str) -> FeatureSource:
    """The task's source of feature ``name``, or one line saying the task cannot provide it."""
    if name not in sources:
        offered = ", ".join(sorted(sources)) or "none"
        raise DataError(f"{path}: the policy reads {name!r}, which task {task!r} cannot provide (it provides {offered})")
    return sources[name]


def check_width(source: FeatureSource, name: str, width: int, path: str, task: str) -> None:
    if source.width is not None and source.width != width:
        raise DataError(f"{path}: the policy reads {name!r} of {width} values; task {task!r} provides "
                        f"{source.width} ({source.key}{'' if source.take is None else f'[:{source.take}]'})")


def padded(source: FeatureSource, scale: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A feature's affine map over the whole key it comes from: identity beyond the leading ``take`` entries."""
    if source.take is None or source.shape is None:
        shape = source.shape or scale.shape
        return scale.reshape(shape), offset.reshape(shape)
    full_s, full_o = np.ones(source.shape, dtype=np.float64), np.zeros(source.shape, dtype=np.float64)
    full_s.reshape(-1)[: source.take] = scale.reshape(-1)
    full_o.reshape(-1)[: source.take] = offset.reshape(-1)
    return full_s, full_o


def checked_config(make: Any, path: str) -> PolicyConfig:
    """``make()``'s PolicyConfig; an impossible combination is one line naming the file."""
    try:
        return make()
    except ValueError as exc:
        raise DataError(f"{path}: {exc}") from None
