"""The DreamerV3-style latent world model as one LightningModule, and the scorer that ranks proposals in imagination.

Training reads sequences of ``config.sequence`` steps (observations, actions, the task's state and
reward there), filters them through the RSSM with the posterior, and minimises DreamerV3's loss:
the decoder's error on the normalised state, the reward head's on the symlog of the scaled reward,
and the balanced, free-bit-clipped KL terms. A decision starts from the posterior of the current
observation, stacked with the ``config.history - 1`` before it (the model state a training sequence
starts from: no state before it), rolls each of the K chunks out with the prior's most likely latents,
and scores the rewards it imagines (``config.aggregate``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gpc.datasets.datamodule import DataConfig
from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.latent.config import LatentConfig
from gpc.models.latent.rssm import RSSM, kl, symexp, symlog
from gpc.models.rewards.stored import reward_scale, stored_reward
from gpc.models.training.config import RunConfig
from gpc.models.training.module import Batch, Logs
from gpc.models.training.observing import ObservingModule

KIND = "latent-world-model"
ACTION_KEY, STATE_KEY, GOAL_KEY, IMAGE_KEY = "action", "state", "goal", "img"


class LatentWorldModelModule(ObservingModule):
    """An RSSM for one task and observation type; also the ``Scorer`` its planner (``dreamer``) ranks with."""

    KIND, WHAT, CONFIG = KIND, "latent world model", LatentConfig

    def __init__(self, config: LatentConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = LatentConfig.from_dict(config)
        if not config.encoder.obs_shapes or config.state_dim < 1:
            raise ValueError("latent world model config has no observation shapes; train it on stores")
        super().__init__(config, data)
        self.config: LatentConfig = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.model = RSSM(config, config.state_dim)

    @property
    def n_obs_steps(self) -> int:
        """A decision starts from the posterior of the current observation (and the ``history - 1`` before it)."""
        return self.config.history

    @classmethod
    def data_config(cls, config: LatentConfig, datasets: tuple[str, ...], run: RunConfig, split: tuple[int, float]) -> DataConfig:
        keys = config.obs_keys + (STATE_KEY,) + ((GOAL_KEY,) if config.reward_goal else ())
        length = config.sequence + config.history - 1  # the first history - 1 steps are only read, stacked
        return DataConfig(paths=datasets, obs_keys=tuple(dict.fromkeys(keys)), horizon=length, n_obs_steps=config.history,
                          n_action_steps=1, obs_steps_override=length, val_ratio=split[1], seed=split[0],
                          batch_size=run.batch_size, num_workers=run.num_workers)

    @classmethod
    def fit_to_data(cls, config: LatentConfig, arrays: EpisodeArrays, source: str, resumed: bool) -> LatentConfig:
        """Observation shapes and the state's width from the stores, and the reward's scale over every stored step."""
        state_dim = int(arrays.data[STATE_KEY].shape[1])
        if resumed:
            if config.state_dim != state_dim:
                raise DataError(f"{source}: the run was trained on states of {config.state_dim} entries, the datasets have {state_dim}")
            return config.fitted_to(arrays.data, source, fixed=True)
        goals = arrays.data[GOAL_KEY] if config.reward_goal else None
        scale = reward_scale(config.reward, config.task, arrays.data[STATE_KEY], goals)
        return dataclasses.replace(config.fitted_to(arrays.data, source, fixed=False), state_dim=state_dim, reward_scale=scale)

    def check_ready(self) -> None:
        missing = [k for k in self.obs_keys + (ACTION_KEY, STATE_KEY) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the normaliser has no statistics for {', '.join(missing)} (build it from the data)")

    def _embed(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """``{key: (B, T, ...)}`` raw -> ``(B, T - history + 1, hidden)`` embeddings, each of its step and the
        ``history - 1`` before it."""
        features, n = self.model.encoder(self._obs(obs)), self.config.history
        length = features.shape[1] - n + 1
        return self.model.embed(torch.cat([features[:, i : i + length] for i in range(n)], dim=-1))

    def loss(self, batch: Batch) -> tuple[torch.Tensor, Logs]:
        cfg, net = self.config, self.model
        embedding = self._embed(batch)
        skip = cfg.history - 1  # steps read only as the first embeddings' history
        actions = self.normalizer.normalize(ACTION_KEY, batch[ACTION_KEY][:, skip:].float())
        states = batch[STATE_KEY][:, skip:].float()
        b, length = states.shape[:2]
        goal = batch[GOAL_KEY][:, skip:].float().flatten(0, 1) if cfg.reward_goal else None
        with torch.no_grad():
            reward = stored_reward(cfg.reward, cfg.task)(states.flatten(0, 1)[:, None], goal).unflatten(0, (b, length))
        h, z = net.initial(b, states.device)
        hs, zs, posts, priors = [], [], [], []
        for t in range(length):
            if t:
                h = net.step(h, z, actions[:, t - 1])
            priors.append(net.probs(net.prior(h)))
            post, z = net.observe(h, embedding[:, t])
            hs.append(h)
            zs.append(z)
            posts.append(post)
        decoded, predicted = net.heads(torch.stack(hs, 1), torch.stack(zs, 1))
        post, prior = torch.stack(posts, 1), torch.stack(priors, 1)
        recon = (decoded - self.normalizer.normalize(STATE_KEY, states)).pow(2).sum(-1).mean()
        reward_loss = F.mse_loss(predicted, symlog(reward / cfg.reward_scale))
        dyn = kl(post.detach(), prior).clamp_min(cfg.free_nats).mean()
        rep = kl(post, prior.detach()).clamp_min(cfg.free_nats).mean()
        loss = cfg.recon_weight * recon + cfg.reward_weight * reward_loss + cfg.dyn_scale * dyn + cfg.rep_scale * rep
        return loss, {"recon": recon.detach(), "reward_loss": reward_loss.detach(), "kl": dyn.detach()}

    # ------------------------------------------------------------------ imagination (the Scorer protocol)
    @torch.no_grad()
    def imagine(self, obs: Mapping[str, Any], chunks: torch.Tensor) -> torch.Tensor:
        """``{key: (B, T, ...)}`` raw histories, ``(B, K, T', A)`` raw chunks -> ``(B, K, T')`` imagined rewards."""
        net = self.model
        n = self.config.history
        embedding = self._embed({k: torch.as_tensor(np.asarray(v))[:, -n:] for k, v in obs.items() if k in self.obs_keys})[:, 0]
        b, k, steps = chunks.shape[:3]
        h, _ = net.initial(b, embedding.device)
        _, z = net.observe(h, embedding, mode=True)
        h, z = h.repeat_interleave(k, 0), z.repeat_interleave(k, 0)
        actions = self.normalizer.normalize(ACTION_KEY, chunks.to(embedding.device, torch.float32)).flatten(0, 1)
        rewards = []
        for i in range(steps):
            h = net.step(h, z, actions[:, i])
            _, z = net.imagine(h, mode=True)
            rewards.append(symexp(net.heads(h, z)[1]) * self.config.reward_scale)
        return torch.stack(rewards, -1).unflatten(0, (b, k))

    def score(self, rewards: torch.Tensor) -> torch.Tensor:
        """``(B, K, T')`` imagined rewards -> ``(B, K)`` by ``config.aggregate``."""
        if self.config.aggregate == "final":
            return rewards[..., -1]
        weights = self.config.discount ** torch.arange(rewards.shape[-1], dtype=rewards.dtype, device=rewards.device)
        return (rewards * weights).sum(-1)

    def objective(self, obs: Mapping[str, np.ndarray], timer: Any, episodes: Sequence[int] | None = None) -> Any:
        """One decision's objective: ``(B, K, T, A)`` chunks -> scores ``(B, K)`` and the imagined rewards ``(B, K, T)``."""

        def score(chunks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            with timer("world_model"):
                rewards = self.imagine(obs, chunks).to(chunks.device)
            return self.score(rewards), rewards

        return score


def load_latent(path: str, task: Any = None, device: str = "cpu") -> LatentWorldModelModule:
    """A latent world-model checkpoint (``gpc train latent-world-model``) on ``device``, of ``task`` when given."""
    name = getattr(task, "name", task)
    return LatentWorldModelModule.load_from_checkpoint(path, map_location=device, task=name).to(device)
