"""V-GPS's value function as one LightningModule: IQL on stored episodes, and a scorer that ranks proposals by Q.

One transition is one decision: the observation history at step t, the chunk of ``n_action_steps``
actions executed from t, the task's reward on the state it reaches (step t + n) and the history
there. IQL (Kostrikov et al. 2022) then fits

- V(s) to the ``expectile`` of the target Q(s, a) over the data's chunks (the better chunks' value,
  never an action the data lacks), and
- two Q(s, a) to r + discount**n * V(s') (clipped double Q: the target is their minimum),

with the target Q-networks the training contract's exponential average of the trained ones
(``ValueConfig.ema``). At a decision the averaged Q (the minimum of its two heads) scores each
of the policy's K proposals by its first ``n_action_steps`` actions (``gpc.models.planning``'s
``Rank`` keeps the best): that is V-GPS's re-ranking.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from gpc.datasets.datamodule import DataConfig
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.networks.encoders import ObsEncoder
from gpc.models.networks.mlp import MLP
from gpc.models.rewards.stored import reward_scale, stored_reward
from gpc.models.training.config import RunConfig
from gpc.models.training.module import Batch, Logs
from gpc.models.training.observing import ObservingModule
from gpc.models.values.config import ValueConfig

KIND = "value"
ACTION_KEY, STATE_KEY, GOAL_KEY, IMAGE_KEY = "action", "state", "goal", "img"


class ValueNetwork(nn.Module):
    """Observation encoder (the policy's kind) + two Q heads on (features, chunk) + a V head on the features."""

    def __init__(self, config: ValueConfig) -> None:
        super().__init__()
        self.encoder = ObsEncoder(config.encoder)
        features = self.encoder.feature_dim * config.n_obs_steps
        chunk = config.n_action_steps * config.action_dim
        self.q = nn.ModuleList([MLP(features + chunk, 1, config.width, config.depth, "relu", layer_norm=True) for _ in range(2)])
        self.v = MLP(features, 1, config.width, config.depth, "relu", layer_norm=True)

    def features(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``{key: (B, H, ...)}`` normalised -> ``(B, F)``."""
        return self.encoder(dict(obs)).flatten(1)

    def q_values(self, features: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """``(N, F)``, ``(N, n * A)`` normalised -> ``(2, N)``."""
        x = torch.cat([features, chunk], dim=-1)
        return torch.stack([head(x)[..., 0] for head in cast(Sequence[MLP], self.q)])

    def value(self, features: torch.Tensor) -> torch.Tensor:
        return self.v(features)[..., 0]


def expectile_loss(diff: torch.Tensor, tau: float) -> torch.Tensor:
    """IQL's asymmetric square: ``|tau - 1(diff < 0)| * diff**2``, averaged."""
    weight = torch.where(diff < 0, 1.0 - tau, tau)
    return (weight * diff.pow(2)).mean()


class ValueModule(ObservingModule):
    """V-GPS's Q-function for one task and observation type; also the ``Scorer`` its planner ranks with."""

    KIND, WHAT, CONFIG = KIND, "value function", ValueConfig

    def __init__(self, config: ValueConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = ValueConfig.from_dict(config)
        if not config.encoder.obs_shapes:
            raise ValueError("value config has no observation shapes; train it on stores (gpc train value)")
        super().__init__(config, data)
        self.config: ValueConfig = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.model = ValueNetwork(config)
        self.track_ema()
        self._reward: Any = None

    @property
    def n_obs_steps(self) -> int:
        return self.config.n_obs_steps

    @classmethod
    def data_config(cls, config: ValueConfig, datasets: tuple[str, ...], run: RunConfig, split: tuple[int, float]) -> DataConfig:
        """Windows of ``n_obs_steps + n_action_steps`` steps: the history, the chunk, the history after it."""
        h, n = config.n_obs_steps, config.n_action_steps
        keys = config.obs_keys + (STATE_KEY,) + ((GOAL_KEY,) if config.reward_goal else ())
        return DataConfig(paths=datasets, obs_keys=tuple(dict.fromkeys(keys)), horizon=h + n, n_obs_steps=h, n_action_steps=n,
                          obs_steps_override=h + n, val_ratio=split[1], seed=split[0], batch_size=run.batch_size,
                          num_workers=run.num_workers)

    @classmethod
    def fit_to_data(cls, config: ValueConfig, arrays: EpisodeArrays, source: str, resumed: bool) -> ValueConfig:
        """Observation shapes from the stores, and the reward's scale (its standard deviation over every stored step)."""
        import dataclasses

        if resumed:
            return config.fitted_to(arrays.data, source, fixed=True)
        goals = arrays.data[GOAL_KEY] if config.reward_goal else None
        scale = reward_scale(config.reward, config.task, arrays.data[STATE_KEY], goals)
        return dataclasses.replace(config.fitted_to(arrays.data, source, fixed=False), reward_scale=scale)

    def check_ready(self) -> None:
        keys = self.obs_keys + (ACTION_KEY,)
        missing = [k for k in keys if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the normaliser has no statistics for {', '.join(missing)} (build it from the data)")

    def _steps(self, obs: Mapping[str, Any], steps: slice) -> dict[str, torch.Tensor]:
        return {k: v[:, steps] for k, v in self._obs(obs).items()}

    def _chunk(self, actions: torch.Tensor) -> torch.Tensor:
        """``(..., n, A)`` raw actions -> ``(..., n * A)`` normalised."""
        return self.normalizer.normalize(ACTION_KEY, actions.to(self.device, torch.float32)).flatten(-2)

    def loss(self, batch: Batch) -> tuple[torch.Tensor, Logs]:
        cfg = self.config
        h, n = cfg.n_obs_steps, cfg.n_action_steps
        now, after = self._steps(batch, slice(0, h)), self._steps(batch, slice(n, n + h))
        chunk = self._chunk(batch[ACTION_KEY][:, h - 1 : h - 1 + n])
        goal = batch[GOAL_KEY][:, h - 1].float() if cfg.reward_goal else None
        with torch.no_grad():
            reward = stored_reward(cfg.reward, cfg.task)(batch[STATE_KEY][:, h : h + n].float(), goal) / cfg.reward_scale
            target_net = cast(ValueNetwork, self.ema.model if self.ema is not None else self.model)
            target_q = target_net.q_values(target_net.features(now), chunk).min(dim=0).values
            backup = reward + cfg.chunk_discount * self.model.value(self.model.features(after))
        features = self.model.features(now)
        v = self.model.value(features.detach())
        v_loss = expectile_loss(target_q - v, cfg.expectile)
        q = self.model.q_values(features, chunk)
        q_loss = (q - backup).pow(2).mean(dim=1).sum()
        logs = {"q_loss": q_loss.detach(), "v_loss": v_loss.detach(), "q": q.detach().mean(), "reward": reward.mean()}
        return q_loss + v_loss, logs

    # ------------------------------------------------------------------ scoring (the Scorer protocol)
    @torch.no_grad()
    def q(self, obs: Mapping[str, Any], chunks: torch.Tensor) -> torch.Tensor:
        """``{key: (B, T >= H, ...)}`` raw histories, ``(B, K, T', A)`` raw chunks from now on -> ``(B, K)`` Q (the averaged
        networks, the minimum of the two heads) of each chunk's first ``n_action_steps`` actions, in reward units."""
        n = self.config.n_action_steps
        if chunks.shape[2] < n:
            raise ValueError(f"chunks of {chunks.shape[2]} actions; the value function scores {n}")
        net = cast(ValueNetwork, self.ema.model if self.ema is not None else self.model)
        history = {k: v[:, -self.config.n_obs_steps :] for k, v in self._obs(obs).items()}
        b, k = chunks.shape[:2]
        features = net.features(history).repeat_interleave(k, dim=0)
        q = net.q_values(features, self._chunk(chunks[:, :, :n]).flatten(0, 1)).min(dim=0).values
        return q.unflatten(0, (b, k)) * self.config.reward_scale

    def objective(self, obs: Mapping[str, np.ndarray], timer: Any, episodes: Sequence[int] | None = None) -> Any:
        """One decision's objective: ``(B, K, T, A)`` chunks -> their Q ``(B, K)`` and, as the prediction, Q again."""

        def score(chunks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            with timer("value"):
                q = self.q(obs, chunks).to(chunks.device)
            return q, q[..., None]

        return score


def load_value(path: str, task: Any = None, device: str = "cpu") -> ValueModule:
    """A value checkpoint (``gpc train value``) on ``device``; ``task``: the one it must belong to (its ``name``)."""
    name = getattr(task, "name", task)
    return ValueModule.load_from_checkpoint(path, map_location=device, task=name).to(device)
