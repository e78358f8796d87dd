"""The LaDi-WM-style world model as one LightningModule, and the scorer that ranks proposals by predicted latents.

Training windows hold the history, the chunk and the observations after each of its first
``future`` actions. The policy's frozen encoder (and its normaliser) turn observations into
latents, scaled to [-1, 1] by their range over the training data; a 1-D U-Net learns DDPM's noise
prediction on the future latents (by default their change since now, scaled by the largest change
``future`` steps bring in the data: the latents move little over a chunk, so denoising them whole
spends the model's precision on what nothing changes), conditioned on the history's latents and the
actions, and a reward head learns the task's reward (symlog of the scaled reward) from a latent. A
decision samples the K chunks' futures with DDIM from one fixed noise draw shared by the K (the same
latents for the same inputs, and proposals differ by their actions, not their noise) and scores the
last predicted latent's reward (``config.aggregate``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F
from rich.progress import track
from torch import nn

from gpc.datasets.datamodule import DataConfig, EpisodeDataModule
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.ladi.config import LadiConfig
from gpc.models.latent.rssm import symexp, symlog
from gpc.models.networks.ddpm import DiffusionSampler, NoiseSchedule
from gpc.models.networks.encoders import ObsEncoder
from gpc.models.networks.mlp import MLP
from gpc.models.networks.unet1d import ConditionalUnet1D
from gpc.models.rewards.stored import reward_scale, stored_reward
from gpc.models.training.config import RunConfig
from gpc.models.training.module import Batch, Logs
from gpc.models.training.observing import ObservingModule

KIND = "ladi-world-model"
ACTION_KEY, STATE_KEY, GOAL_KEY, IMAGE_KEY = "action", "state", "goal", "img"
FEATURE_KEY = "ladi_features"  # the frozen encoder's features of every stored step, when it has weights to run
SAMPLING_SEED = 0  # the noise every decision's futures start from (scores repeat for the same inputs)


class LadiNetwork(nn.Module):
    """The frozen encoder, the latent denoiser and the reward head; latents are scaled by ``low``/``high``."""

    low: torch.Tensor
    high: torch.Tensor
    reach: torch.Tensor

    def __init__(self, config: LadiConfig) -> None:
        super().__init__()
        self.encoder = ObsEncoder(config.encoder).requires_grad_(False)
        width = self.encoder.feature_dim
        cond = width * config.n_obs_steps + config.action_dim * config.future
        self.unet = ConditionalUnet1D(config.unet, width, cond)
        self.reward = MLP(width, 1, config.reward_width, 2, "silu", layer_norm=True)
        self.schedule = NoiseSchedule(config.noise)
        self.register_buffer("low", -torch.ones(width))
        self.register_buffer("high", torch.ones(width))
        self.register_buffer("reach", torch.ones(width))  # per latent, the largest change over `future` steps (target "change")
        self.change = config.target == "change"

    def latents(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``{key: (B, T, ...)}`` normalised observations -> ``(B, T, F)`` latents in [-1, 1] (the encoder frozen)."""
        with torch.no_grad():
            return self.scaled(self.encoder(dict(obs)))

    def scaled(self, features: torch.Tensor) -> torch.Tensor:
        """The encoder's features -> latents in [-1, 1] over the training data's range."""
        return 2.0 * (features - self.low) / (self.high - self.low).clamp_min(1e-6) - 1.0

    def target(self, history: torch.Tensor, future: torch.Tensor) -> torch.Tensor:
        """``(B, H, F)``, ``(B, n, F)`` latents -> what the U-Net denoises: the future, or its change since now."""
        return (future - history[:, -1:]) / self.reach.clamp_min(1e-6) if self.change else future

    def future(self, history: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
        """The inverse of ``target``: a denoised sample -> the future latents."""
        return history[:, -1:] + sample * self.reach.clamp_min(1e-6) if self.change else sample


class LadiModule(ObservingModule):
    """A latent diffusion world model over the policy's frozen encoder; also the ``Scorer`` of ``--planner ladi``."""

    KIND, WHAT, CONFIG = KIND, "latent diffusion world model", LadiConfig

    def __init__(self, config: LadiConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = LadiConfig.from_dict(config)
        if not config.encoder.obs_shapes:
            raise ValueError("latent diffusion config has no observation shapes; take them from the policy")
        super().__init__(config, data)
        self.config: LadiConfig = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.model = LadiNetwork(config)
        self.track_ema()

    @property
    def n_obs_steps(self) -> int:
        return self.config.n_obs_steps

    @classmethod
    def data_config(cls, config: LadiConfig, datasets: tuple[str, ...], run: RunConfig, split: tuple[int, float]) -> DataConfig:
        h = config.n_obs_steps
        keys = config.obs_keys + (STATE_KEY,) + ((GOAL_KEY,) if config.reward_goal else ())
        return DataConfig(paths=datasets, obs_keys=tuple(dict.fromkeys(keys)), horizon=h + config.future, n_obs_steps=h,
                          n_action_steps=1, obs_steps_override=h + config.future, val_ratio=split[1], seed=split[0],
                          batch_size=run.batch_size, num_workers=run.num_workers)

    @classmethod
    def fit_to_data(cls, config: LadiConfig, arrays: EpisodeArrays, source: str, resumed: bool) -> LadiConfig:
        """The stores must hold what the policy's encoder reads; the reward's scale comes from their states."""
        config = config.fitted_to(arrays.data, source, fixed=True)  # the policy's encoder, as it was built
        if resumed:
            return config
        goals = arrays.data[GOAL_KEY] if config.reward_goal else None
        return dataclasses.replace(config, reward_scale=reward_scale(config.reward, config.task, arrays.data[STATE_KEY], goals))

    @classmethod
    def from_data(cls, config: LadiConfig, data: EpisodeDataModule, record: dict[str, Any]) -> LadiModule:
        """The policy's normaliser and averaged encoder weights, frozen; the latents' range over training steps."""
        from gpc.models.policy.module import PolicyModule

        policy = PolicyModule.load_from_checkpoint(config.policy, task=config.task)
        module = cls(config, normalizer=policy.normalizer, data=record)
        source = cast(Any, policy.ema.model if policy.ema is not None else policy.model).encoder
        module.model.encoder.load_state_dict(source.state_dict())
        module.model.eval()  # the bounds come from the features a decision reads
        with torch.no_grad():
            n = len(data.arrays.data[STATE_KEY])
            features = module._features(data.arrays.data, np.sort(np.random.default_rng(0).choice(n, size=min(4096, n), replace=False)))
            module.model.low.copy_(features.min(dim=0).values)
            module.model.high.copy_(features.max(dim=0).values)
            module.model.reach.copy_(module._reach(data.arrays))
        module.model.train()
        if module.ema is not None:
            module.ema.update(module.model)  # the averaged copy starts from these weights and bounds
        return module

    def _features(self, arrays: Mapping[str, np.ndarray], steps: np.ndarray, progress: str = "") -> torch.Tensor:
        """The frozen encoder's ``(len(steps), F)`` features of stored steps, 512 at a time."""
        parts, starts = [], range(0, len(steps), 512)
        for start in track(starts, progress, total=len(starts), disable=not progress):
            part = {k: torch.as_tensor(arrays[k][steps[start : start + 512]], dtype=torch.float32)[:, None] for k in self.obs_keys}
            parts.append(self.model.encoder(self._obs(part))[:, 0])
        return torch.cat(parts)

    def _reach(self, arrays: EpisodeArrays) -> torch.Tensor:
        """Per latent, the largest change ``future`` steps bring within an episode, over up to 4,096 sampled steps."""
        ends, future = arrays.episode_ends, self.config.future
        steps = np.arange(len(arrays.data[STATE_KEY]))
        steps = steps[steps + future < ends[np.searchsorted(ends, steps, side="right")]]
        if not steps.size:
            return torch.ones_like(self.model.reach)
        steps = np.sort(np.random.default_rng(1).choice(steps, size=min(4096, steps.size), replace=False))
        now, later = (self.model.scaled(self._features(arrays.data, s)) for s in (steps, steps + future))
        return (later - now).abs().max(dim=0).values

    def check_ready(self) -> None:
        missing = [k for k in self.obs_keys + (ACTION_KEY,) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the normaliser has no statistics for {', '.join(missing)} (build it from the policy)")

    @torch.no_grad()
    def prepare(self, data: EpisodeDataModule, progress: bool = False) -> None:
        """An encoder with weights (an image policy's ResNet) is frozen, so each stored frame's features are computed
        once, in eval mode as at a decision, and windows read those instead of frames: otherwise every window
        encodes its history and future again (2,560 frames per batch of 256)."""
        encoder = self.model.encoder
        if not any(True for _ in encoder.parameters()):
            return
        arrays, mode = data.arrays.data, encoder.training
        encoder.eval()
        steps = np.arange(len(arrays[STATE_KEY]))
        arrays[FEATURE_KEY] = self._features(arrays, steps, "frozen encoder: every stored frame" if progress else "").cpu().numpy()
        encoder.train(mode)
        only_encoded = set(self.obs_keys) - {STATE_KEY, GOAL_KEY}  # the reward still reads the states (and goals)
        data.steps = {k: v for k, v in data.steps.items() if k not in only_encoded} | {FEATURE_KEY: data.steps[self.obs_keys[0]]}

    def loss(self, batch: Batch) -> tuple[torch.Tensor, Logs]:
        cfg, net = self.config, self.model
        h, n = cfg.n_obs_steps, cfg.future
        latents = net.scaled(batch[FEATURE_KEY].to(self.device)) if FEATURE_KEY in batch else net.latents(self._obs(batch))
        actions = self.normalizer.normalize(ACTION_KEY, batch[ACTION_KEY][:, h - 1 : h - 1 + n].float())
        cond = torch.cat([latents[:, :h].flatten(1), actions.flatten(1)], dim=-1)
        target = net.target(latents[:, :h], latents[:, h:])
        noise = torch.randn_like(target)
        t = torch.randint(0, net.schedule.train_steps, (target.shape[0],), device=target.device)
        denoise = F.mse_loss(net.unet(net.schedule.add_noise(target, noise, t), t, cond), net.schedule.target(target, noise))
        states = batch[STATE_KEY].float()
        goal = batch[GOAL_KEY].float().flatten(0, 1) if cfg.reward_goal else None
        with torch.no_grad():
            reward = stored_reward(cfg.reward, cfg.task)(states.flatten(0, 1)[:, None], goal).unflatten(0, states.shape[:2])
        reward_loss = F.mse_loss(net.reward(latents)[..., 0], symlog(reward / cfg.reward_scale))
        return denoise + reward_loss, {"denoise": denoise.detach(), "reward_loss": reward_loss.detach()}

    # ------------------------------------------------------------------ prediction (the Scorer protocol)
    @torch.no_grad()
    def predict(self, obs: Mapping[str, Any], chunks: torch.Tensor) -> torch.Tensor:
        """``{key: (B, T >= H, ...)}`` raw histories, ``(B, K, T', A)`` raw chunks -> ``(B, K, future, F)`` latents."""
        cfg = self.config
        if chunks.shape[2] < cfg.future:
            raise ValueError(f"chunks of {chunks.shape[2]} actions; the model predicts after {cfg.future}")
        net = cast(LadiNetwork, self.ema.model if self.ema is not None else self.model)
        history = net.latents({k: v[:, -cfg.n_obs_steps :] for k, v in self._obs(obs).items()})
        b, k = chunks.shape[:2]
        actions = self.normalizer.normalize(ACTION_KEY, chunks[:, :, : cfg.future].to(self.device, torch.float32))
        cond = torch.cat([history.flatten(1).repeat_interleave(k, 0), actions.flatten(0, 1).flatten(1)], dim=-1)
        generator = torch.Generator().manual_seed(SAMPLING_SEED)
        shape = (b, 1, cfg.future, history.shape[-1])
        draw = lambda: torch.randn(shape, generator=generator).expand(b, k, *shape[2:]).flatten(0, 1).to(self.device)  # noqa: E731
        steps = torch.empty(b * k, dtype=torch.long, device=self.device)
        sampler = DiffusionSampler(net.schedule, cfg.sampler)
        sample = sampler.sample(lambda x, t: net.unet(x, steps.fill_(t), cond), draw(), draw)
        return net.future(history.repeat_interleave(k, 0), sample).unflatten(0, (b, k))

    def rewards(self, latents: torch.Tensor) -> torch.Tensor:
        """``(..., F)`` latents -> ``(...)`` rewards in the task's units."""
        net = cast(LadiNetwork, self.ema.model if self.ema is not None else self.model)
        return symexp(net.reward(latents)[..., 0]) * self.config.reward_scale

    def objective(self, obs: Mapping[str, np.ndarray], timer: Any, episodes: Sequence[int] | None = None) -> Any:
        """One decision's objective: ``(B, K, T, A)`` chunks -> scores ``(B, K)`` and the predicted latents."""

        def score(chunks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            with timer("world_model"):
                latents = self.predict(obs, chunks)
            with torch.no_grad(), timer("reward"):
                rewards = self.rewards(latents)
            scores = rewards[..., -1] if self.config.aggregate == "final" else rewards.sum(-1)
            return scores.to(chunks.device), latents.to(chunks.device)

        return score


def load_ladi(path: str, task: Any = None, device: str = "cpu") -> LadiModule:
    """A latent diffusion world-model checkpoint on ``device``, of ``task`` when given."""
    name = getattr(task, "name", task)
    return LadiModule.load_from_checkpoint(path, map_location=device, task=name).to(device)
