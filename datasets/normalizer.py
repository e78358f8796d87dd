"""Per-key min-max normalisation to [-1, 1], as an ``nn.Module`` so statistics ride in checkpoints."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import nn

_RANGE_EPS = 1e-4


class MinMaxNormalizer(nn.Module):
    """Maps each key's feature-wise ``[min, max]`` to ``[-1, 1]``; constant features map to 0.

    Images (uint8 0..255) use the fixed range rather than data statistics, so an unseen
    colour can never fall outside the network's input range.
    """

    def __init__(self) -> None:
        super().__init__()
        self.scales = nn.ParameterDict()
        self.offsets = nn.ParameterDict()

    @classmethod
    def fit(cls, data: dict[str, np.ndarray], image_keys: tuple[str, ...] = (),
            spans: Mapping[str, Sequence[tuple[int, float, float]]] | None = None) -> MinMaxNormalizer:
        """``spans``: per key, ``(feature, low, high)`` ranges each feature's span covers at least (a task's declared
        range of a feature its data barely varies, ``StateLayout.spans``)."""
        norm = cls()
        for key, value in data.items():
            if key in image_keys:
                lo, hi = np.zeros(value.shape[-1]), np.full(value.shape[-1], 255.0)
            else:
                value = np.asarray(value, dtype=np.float64)
                lo, hi = value.min(axis=0), value.max(axis=0)
                for i, low, high in (spans or {}).get(key, ()):
                    lo[i], hi[i] = min(lo[i], low), max(hi[i], high)
            norm.add(key, lo, hi)
        return norm

    def add(self, key: str, lo: np.ndarray, hi: np.ndarray) -> None:
        rng = hi - lo
        flat = rng < _RANGE_EPS
        scale = np.where(flat, 1.0, 2.0 / np.where(flat, 1.0, rng))
        offset = np.where(flat, -lo, -1.0 - scale * lo)
        self.add_affine(key, scale, offset)

    def add_affine(self, key: str, scale: np.ndarray, offset: np.ndarray) -> None:
        """``x * scale + offset`` for ``key`` as given: any per-feature affine map (another framework's
        mean-std or min-max statistics, converted once)."""
        self.scales[key] = nn.Parameter(torch.as_tensor(scale, dtype=torch.float32), requires_grad=False)
        self.offsets[key] = nn.Parameter(torch.as_tensor(offset, dtype=torch.float32), requires_grad=False)

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        """``x`` of shape ``(..., *feature_shape)``; statistics broadcast over leading dims."""
        return x * self.scales[key] + self.offsets[key]

    def unnormalize(self, key: str, y: torch.Tensor) -> torch.Tensor:
        return (y - self.offsets[key]) / self.scales[key]

    def keys(self) -> list[str]:
        return list(self.scales.keys())

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys,
                              unexpected_keys, error_msgs) -> None:
        # Keys are data-dependent, so a freshly built normalizer learns them from the checkpoint.
        for name in ("scales", "offsets"):
            store = getattr(self, name)
            head = f"{prefix}{name}."
            for full, tensor in state_dict.items():
                if full.startswith(head) and full[len(head):] not in store:
                    store[full[len(head):]] = nn.Parameter(torch.empty_like(tensor), requires_grad=False)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys,
                                      unexpected_keys, error_msgs)
