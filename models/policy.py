"""Diffusion Policy as one LightningModule: batch in, loss and logs out; K proposals per history out.

The module owns the normaliser (its statistics ride in the state dict), the training
network, its EMA copy (used for validation and sampling) and the checkpoint record
(``kind="policy"``, task, obs type). ``PolicyModule.load_from_checkpoint(path)`` alone
rebuilds all of it.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Any, Iterator, Mapping, Sequence

import lightning as L
import numpy as np
import torch
from torch import nn

from datasets.normalizer import MinMaxNormalizer
from models.checkpoint import checkpoint_meta, read_checkpoint, rebuild
from models.denoiser import ActionDenoiser
from models.diffusion import DiffusionSampler, SamplerConfig
from models.ema import EMAWeights
from models.optim import adamw_cosine
from models.policy_config import PolicyConfig

KIND = "policy"
ACTION_KEY = "action"
Generators = torch.Generator | Sequence[torch.Generator] | None


@contextmanager
def _eval_mode(module: nn.Module) -> Iterator[None]:
    was = module.training
    module.eval()
    try:
        yield
    finally:
        module.train(was)


class PolicyModule(L.LightningModule):
    """Diffusion Policy for one task and observation type (``config.encoder.obs_type``)."""

    def __init__(self, config: PolicyConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None) -> None:
        super().__init__()
        self.config = PolicyConfig.from_dict(config)
        if not self.config.encoder.obs_shapes:
            raise ValueError("policy config has no observation shapes; fill them with config.with_obs_shapes(...)")
        self.save_hyperparameters({"config": self.config.to_dict()})
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.model = ActionDenoiser(self.config)
        self.ema = EMAWeights(self.model, self.config.ema)
        self.diverged_at: int | None = None  # global step of a non-finite loss; training stops there

    # ------------------------------------------------------------------ properties
    @property
    def obs_keys(self) -> tuple[str, ...]:
        return self.config.obs_keys

    @property
    def action_slice(self) -> slice:
        """The actions of a chunk to execute: ``n_action_steps`` from index ``n_obs_steps - 1``."""
        start = self.config.n_obs_steps - 1
        return slice(start, start + self.config.n_action_steps)

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["gpc"] = checkpoint_meta(KIND, self.config.task, obs=self.config.obs_type)

    @classmethod
    def load_from_checkpoint(  # type: ignore[override]
        cls,
        checkpoint_path: str | os.PathLike,
        map_location: Any = "cpu",
        task: str | None = None,
        obs_type: str | None = None,
        **_: Any,
    ) -> "PolicyModule":
        """Rebuild the policy (config, normaliser, weights, EMA) from a checkpoint, in eval mode.

        ``task`` / ``obs_type``, when given, must match the checkpoint's record (DataError otherwise).
        """
        ckpt = read_checkpoint(checkpoint_path, KIND, task=task, map_location=map_location, obs=obs_type)
        return rebuild(cls, ckpt, checkpoint_path, "policy")

    # ------------------------------------------------------------------ data
    def _normalize_obs(self, obs: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        out = {}
        for key in self.obs_keys:
            if key not in obs:
                raise ValueError(f"observation lacks key {key!r} (this policy reads {', '.join(self.obs_keys)})")
            value = torch.as_tensor(np.asarray(obs[key]) if not torch.is_tensor(obs[key]) else obs[key])
            out[key] = self.normalizer.normalize(key, value.to(self.device, torch.float32))
        return out

    def _split_batch(self, batch: Mapping[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        return self._normalize_obs(batch), self.normalizer.normalize(ACTION_KEY, batch[ACTION_KEY].float())

    def on_fit_start(self) -> None:
        missing = [k for k in self.obs_keys + (ACTION_KEY,) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the normaliser has no statistics for {', '.join(missing)} (build it from the data)")

    # ------------------------------------------------------------------ training
    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor | None:
        obs, action = self._split_batch(batch)
        loss, logs = self.model.loss(obs, action)
        bad = not bool(torch.isfinite(loss))
        if self.trainer.strategy.reduce_boolean_decision(bad, all=False):
            # Skip this update (the weights stay the last good ones) and stop; the caller reports it.
            self.diverged_at = self.global_step
            self.trainer.should_stop = True
            return None
        self.log_dict({f"train/{k}": v for k, v in logs.items()}, prog_bar=True, batch_size=action.shape[0])
        return loss

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.diverged_at is None:
            self.log("train/ema_decay", self.ema.update(self.model), batch_size=1)

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        """EMA weights on noise and steps seeded by the batch index, so the metric moves only with the weights."""
        obs, action = self._split_batch(batch)
        loss, _ = self.ema.model.loss(obs, action, generator=torch.Generator().manual_seed(batch_idx))
        self.log("val/loss", loss, prog_bar=True, sync_dist=True, batch_size=action.shape[0])
        return loss

    def configure_optimizers(self) -> dict[str, Any]:
        return adamw_cosine(self.model.parameters(), self.config.optim, self.trainer)

    # ------------------------------------------------------------------ sampling
    def _noise(self, batch: int, shape: tuple[int, ...], generator: Generators) -> torch.Tensor:
        """``(batch * shape[0], *shape[1:])`` standard normal; one generator per history when a sequence."""
        if generator is None:
            return torch.randn((batch * shape[0],) + shape[1:], device=self.device)
        if isinstance(generator, torch.Generator):
            return torch.randn((batch * shape[0],) + shape[1:], generator=generator, device=generator.device).to(self.device)
        return torch.cat([torch.randn(shape, generator=g, device=g.device).to(self.device) for g in generator])

    @torch.no_grad()
    def sample_batch(
        self,
        obs: Mapping[str, Any],
        num_samples: int = 1,
        generator: Generators = None,
        *,
        method: str | None = None,
        steps: int | None = None,
        spacing: str | None = None,
        use_ema: bool = True,
    ) -> torch.Tensor:
        """``{key: (B, T, ...)}`` raw observation histories -> ``(B, K, horizon, action_dim)`` raw actions.

        The last ``n_obs_steps`` of each history are used. ``generator``: one for the whole
        call, or one per history (then history b's proposals equal ``sample`` of it alone
        with that generator). ``method`` / ``steps`` / ``spacing`` override the config's sampler.
        """
        cfg = self.config
        if num_samples < 1:
            raise ValueError(f"num_samples {num_samples}: must be at least 1")
        sampler_cfg = SamplerConfig(method or cfg.sampler.method, steps or cfg.sampler.steps, spacing or cfg.sampler.spacing)
        net = self.ema.model if use_ema else self.model
        sampler = DiffusionSampler(net.schedule, sampler_cfg)
        history = self._normalize_obs(obs)
        b = self._check_history(history)
        if generator is not None and not isinstance(generator, torch.Generator) and len(generator) != b:
            raise ValueError(f"{len(generator)} generators for {b} observation histories")
        history = {k: v[:, -cfg.n_obs_steps :] for k, v in history.items()}
        shape = (num_samples, cfg.horizon, cfg.action_dim)
        with _eval_mode(net):
            cond = net.condition(history).repeat_interleave(num_samples, dim=0)
            t_batch = torch.empty(cond.shape[0], dtype=torch.long, device=self.device)
            x = sampler.sample(
                lambda x, t: net(x, t_batch.fill_(t), cond), self._noise(b, shape, generator),
                lambda: self._noise(b, shape, generator),
            )
        return self.normalizer.unnormalize(ACTION_KEY, x).reshape(b, *shape)

    def sample(self, obs_history: Mapping[str, Any], num_samples: int = 1, generator: torch.Generator | None = None,
               **kwargs: Any) -> torch.Tensor:
        """``{key: (T, ...)}`` one raw observation history -> ``(K, horizon, action_dim)`` raw actions, one batched call."""
        batched = {k: torch.as_tensor(np.asarray(v) if not torch.is_tensor(v) else v)[None] for k, v in obs_history.items()}
        return self.sample_batch(batched, num_samples, None if generator is None else [generator], **kwargs)[0]

    def _check_history(self, history: dict[str, torch.Tensor]) -> int:
        b = None
        for key, value in history.items():
            step = self.config.encoder.shape(key)
            if value.dim() != 2 + len(step) or tuple(value.shape[2:]) != step or value.shape[1] < self.config.n_obs_steps:
                raise ValueError(
                    f"observation {key!r}: expected (B, T >= {self.config.n_obs_steps}, {', '.join(map(str, step))}), "
                    f"got {tuple(value.shape)}"
                )
            if b is not None and value.shape[0] != b:
                raise ValueError(f"observation {key!r}: batch {value.shape[0]} differs from {b}")
            b = value.shape[0]
        return int(b)
