"""What the components that read a policy's observations share (the policy itself; V-GPS's value function and the
latent world models, which score its proposals): the keys they read, how they normalise them, their checkpoint record."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import torch
from torch import nn

from gpc.models.networks.encoders import normalized_obs
from gpc.models.training.module import TrainableModule

STATE_KEY, IMAGE_KEY = "state", "img"


class ObservationModule(TrainableModule):
    """A trainable component that reads ``config.obs_keys`` (normalised by its own normaliser) and trains
    ``self.model``; a subclass names its ``CONFIG`` class."""

    CONFIG: ClassVar[Any]
    model: Any  # the network it trains (the subclass's)
    normalizer: Any

    @property
    def obs_keys(self) -> tuple[str, ...]:
        return tuple(self.config.obs_keys)

    @property
    def network(self) -> nn.Module:
        return self.model

    def record(self) -> dict[str, Any]:
        return {"obs": self.config.obs_type}

    @classmethod
    def config_from_dict(cls, data: Any) -> Any:
        return cls.CONFIG.from_dict(data)

    def _obs(self, obs: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Raw observations -> the keys it reads, normalised, on its device."""
        return normalized_obs(self.normalizer, self.obs_keys, obs, self.device, self.WHAT)


class ObservingModule(ObservationModule):
    """A trainable scorer of a policy's proposals, read from the policy's observations."""

    differentiable = False  # these rank the proposals; none is ascended here

    @property
    def obs_key(self) -> str:
        """The observation family (images or states), for the policy pairing check."""
        return IMAGE_KEY if self.config.obs_type == "image" else STATE_KEY
