"""DreamerV3's recurrent state-space model: GRU state, categorical latents, a decoder and a reward head.

At step t the model state is ``(h_t, z_t)``: ``h_t = GRU(h_{t-1}, [z_{t-1}, a_{t-1}])`` and ``z_t`` is
drawn from the posterior ``q(z | h_t, e_t)`` (``e_t`` the embedding of the observation, stacked with the
``history - 1`` before it) when observed, from the prior ``p(z | h_t)`` when imagined. Latents are
``groups`` one-hot categoricals with a 1% uniform mix, sampled with straight-through gradients. Heads
read ``[h_t, z_t]``: the decoder the normalised state, the reward head the symlog of the scaled reward.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from gpc.models.latent.config import LatentConfig
from gpc.models.networks.encoders import ObsEncoder
from gpc.models.networks.mlp import MLP


def symlog(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.expm1(x.abs())


class RSSM(nn.Module):
    """The latent dynamics and its heads; ``state_dim`` is the decoder's target width."""

    def __init__(self, config: LatentConfig, state_dim: int) -> None:
        super().__init__()
        self.config = config
        c = config
        self.encoder = ObsEncoder(c.encoder)
        self.embed = MLP(self.encoder.feature_dim * c.history, c.hidden, c.hidden, 1, "silu", layer_norm=True)
        self.inp = nn.Sequential(nn.Linear(c.stoch + c.action_dim, c.hidden), nn.LayerNorm(c.hidden), nn.SiLU())
        self.gru = nn.GRUCell(c.hidden, c.deter)
        self.prior = MLP(c.deter, c.stoch, c.hidden, 1, "silu", layer_norm=True)
        self.posterior = MLP(c.deter + c.hidden, c.stoch, c.hidden, 1, "silu", layer_norm=True)
        self.decoder = MLP(c.deter + c.stoch, state_dim, c.hidden, 2, "silu", layer_norm=True)
        self.reward = MLP(c.deter + c.stoch, 1, c.hidden, 2, "silu", layer_norm=True)
        last = self.reward.layers[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)  # DreamerV3 starts its reward head at zero
        nn.init.zeros_(last.bias)

    def probs(self, logits: torch.Tensor) -> torch.Tensor:
        """``(..., stoch)`` logits -> ``(..., groups, classes)`` probabilities with the uniform mix."""
        c = self.config
        p = F.softmax(logits.unflatten(-1, (c.groups, c.classes)), dim=-1)
        return (1.0 - c.unimix) * p + c.unimix / c.classes

    def sample(self, probs: torch.Tensor, mode: bool = False) -> torch.Tensor:
        """One-hot ``(..., stoch)``: a straight-through sample, or the most likely class of each group."""
        if mode:
            return F.one_hot(probs.argmax(-1), self.config.classes).to(probs.dtype).flatten(-2)
        index = torch.distributions.Categorical(probs=probs).sample()
        one_hot = F.one_hot(index, self.config.classes).to(probs.dtype)
        return (one_hot + probs - probs.detach()).flatten(-2)

    def initial(self, batch: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.config
        return torch.zeros(batch, c.deter, device=device), torch.zeros(batch, c.stoch, device=device)

    def step(self, h: torch.Tensor, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The next deterministic state after ``action`` (normalised)."""
        return self.gru(self.inp(torch.cat([z, action], dim=-1)), h)

    def observe(self, h: torch.Tensor, embedding: torch.Tensor, mode: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """The posterior's probabilities and latent at ``h`` given the observation's embedding."""
        probs = self.probs(self.posterior(torch.cat([h, embedding], dim=-1)))
        return probs, self.sample(probs, mode)

    def imagine(self, h: torch.Tensor, mode: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        probs = self.probs(self.prior(h))
        return probs, self.sample(probs, mode)

    def heads(self, h: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The decoded (normalised) state and the symlog of the scaled reward."""
        feat = torch.cat([h, z], dim=-1)
        return self.decoder(feat), self.reward(feat)[..., 0]


def kl(post: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
    """KL(post || prior) of ``(..., groups, classes)`` categoricals, summed over the groups."""
    return (post * (post.clamp_min(1e-8).log() - prior.clamp_min(1e-8).log())).sum(dim=(-1, -2))
