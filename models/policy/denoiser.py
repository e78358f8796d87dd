"""The policy's network: observation encoder + 1-D U-Net, and its DDPM training loss.

Everything here works in normalised units (observations and actions in [-1, 1]); the
LightningModule owns the normaliser and the EMA copy.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gpc.models.networks.ddpm import NoiseSchedule
from gpc.models.networks.encoders import ObsEncoder
from gpc.models.networks.unet1d import ConditionalUnet1D
from gpc.models.policy.config import PolicyConfig


class ActionDenoiser(nn.Module):
    """Predicts the noise in a normalised action chunk, conditioned on an observation history."""

    def __init__(self, config: PolicyConfig) -> None:
        super().__init__()
        self.n_obs_steps = config.n_obs_steps
        self.encoder = ObsEncoder(config.encoder)
        self.unet = ConditionalUnet1D(config.unet, config.action_dim, self.encoder.feature_dim * config.n_obs_steps)
        self.schedule = NoiseSchedule(config.noise)

    def condition(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``{key: (B, T >= n_obs_steps, ...)}`` -> ``(B, n_obs_steps * feature_dim)`` global features."""
        history = {k: v[:, : self.n_obs_steps] for k, v in obs.items()}
        return self.encoder(history).flatten(start_dim=1)

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """``x (B, T, A)`` noisy chunk, ``t (B,)`` steps, ``cond (B, G)`` -> predicted noise (or chunk) ``(B, T, A)``."""
        return self.unet(x, t, cond)

    def loss(
        self, obs: dict[str, torch.Tensor], action: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """MSE to the noise (or the clean chunk) at uniformly drawn steps; ``generator`` makes the draw repeatable.

        ``obs`` values ``(B, T, ...)`` and ``action (B, horizon, A)``, all normalised.
        """
        b = action.shape[0]
        if generator is None:
            noise = torch.randn_like(action)
            t = torch.randint(0, self.schedule.train_steps, (b,), device=action.device)
        else:
            noise = torch.randn(action.shape, generator=generator, device=generator.device).to(action)
            t = torch.randint(0, self.schedule.train_steps, (b,), generator=generator, device=generator.device)
            t = t.to(action.device)
        noisy = self.schedule.add_noise(action, noise, t)
        loss = F.mse_loss(self(noisy, t, self.condition(obs)), self.schedule.target(action, noise))
        return loss, {"loss": loss.detach()}
