"""The small interfaces planners depend on (structural: any object with these methods fits)."""

from __future__ import annotations

from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import torch


@runtime_checkable
class ActionProposer(Protocol):
    """A generative policy: K action chunks for one observation history in one batched call."""

    def sample(
        self, obs_history: Mapping[str, Any], num_samples: int = 1, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """``{key: (T, ...)}`` raw observations -> ``(K, horizon, action_dim)`` raw actions."""
        ...

    def sample_batch(
        self, obs: Mapping[str, Any], num_samples: int = 1,
        generator: torch.Generator | Sequence[torch.Generator] | None = None,
    ) -> torch.Tensor:
        """``{key: (B, T, ...)}`` -> ``(B, K, horizon, action_dim)``; one generator per history repeats ``sample``."""
        ...
