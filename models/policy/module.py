"""Diffusion Policy as one LightningModule: batch in, loss and logs out; K proposals per history out.

The module owns the normaliser (its statistics ride in the state dict) and the training
network; the training contract it shares with every component (``TrainableModule``) adds
the EMA copy (used for validation and sampling) and the checkpoint record (``kind="policy"``,
task, obs type). ``PolicyModule.load_from_checkpoint(path)`` alone rebuilds all of it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from gpc.datasets.datamodule import DataConfig
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.networks.ddpm import DiffusionSampler, SamplerConfig
from gpc.models.policy.config import PolicyConfig
from gpc.models.policy.denoiser import ActionDenoiser
from gpc.models.training.config import RunConfig
from gpc.models.training.observing import ObservationModule

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


class PolicyModule(ObservationModule):
    """Diffusion Policy for one task and observation type (``config.encoder.obs_type``)."""

    KIND, WHAT = "policy", "policy"
    CONFIG = PolicyConfig

    def __init__(self, config: PolicyConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = PolicyConfig.from_dict(config)
        if not config.encoder.obs_shapes:
            raise ValueError("policy config has no observation shapes; fill them with config.with_obs_shapes(...)")
        super().__init__(config, data)
        self.config: PolicyConfig = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.model = ActionDenoiser(config)
        self.track_ema()
        self.source: dict[str, Any] = {"format": "gpc"}  # where the weights came from (a foreign format records its files)

    # ------------------------------------------------------------------ properties
    @property
    def action_slice(self) -> slice:
        """The actions of a chunk to execute: ``n_action_steps`` from index ``n_obs_steps - 1``."""
        start = self.config.n_obs_steps - 1
        return slice(start, start + self.config.n_action_steps)

    # ------------------------------------------------------------------ the training contract
    @classmethod
    def data_config(cls, config: PolicyConfig, datasets: tuple[str, ...], run: RunConfig,
                    split: tuple[int, float]) -> DataConfig:
        return DataConfig(
            paths=datasets, obs_keys=config.obs_keys, horizon=config.horizon, n_obs_steps=config.n_obs_steps,
            n_action_steps=config.n_action_steps, val_ratio=split[1], seed=split[0], batch_size=run.batch_size,
            num_workers=run.num_workers, state_spans=config.encoder.state_spans,
            action_source=None if config.labels == ACTION_KEY else config.labels,
        )

    @classmethod
    def fit_to_data(cls, config: PolicyConfig, arrays: EpisodeArrays, source: str, resumed: bool) -> PolicyConfig:
        """The encoder learns each observation key's step shape from the stores (a resumed run must see the same)."""
        return config.fitted_to(arrays.data, source, fixed=resumed)

    def _split_batch(self, batch: Mapping[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        return self._obs(batch), self.normalizer.normalize(ACTION_KEY, batch[ACTION_KEY].float())

    def check_ready(self) -> None:
        missing = [k for k in self.obs_keys + (ACTION_KEY,) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the normaliser has no statistics for {', '.join(missing)} (build it from the data)")

    def loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        obs, action = self._split_batch(batch)
        return self.model.loss(obs, action)

    def validation_loss(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """EMA weights on noise and steps seeded by the batch index, so the metric moves only with the weights."""
        obs, action = self._split_batch(batch)
        return self._net(use_ema=True).loss(obs, action, generator=torch.Generator().manual_seed(batch_idx))

    def _net(self, use_ema: bool) -> ActionDenoiser:
        """The averaged network (sampling, validation) or the one being trained."""
        return cast(ActionDenoiser, self.ema.model) if use_ema and self.ema is not None else self.model

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
        net = self._net(use_ema)
        sampler = DiffusionSampler(net.schedule, sampler_cfg)
        history = self._obs(obs)
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
        assert b is not None, "no observation keys"
        return int(b)
