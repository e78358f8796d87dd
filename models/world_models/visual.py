"""The visual world model's dynamics: an EDM single-step frame predictor and its batched rollout.

``VisualDynamics`` is to images what ``StateDynamics`` is to states; ``WorldModelModule``
(``gpc.models.world_models.module``) wraps either for training and checkpoints, so both kinds share one
trainer, one checkpoint kind and one evaluation command.

One prediction (H context frames, frameskip ``f``)::

    context   o_{t-(H-1)f} ... o_{t-f} o_t      (frames f steps apart, scaled to [-1, 1])
    actions   a_t ... a_{t+f-1}                 (raw; normalised for the embedding, drawn as maps)
    predicts  o_{t+f}                           (3 Euler steps of the EDM sampler)

A rollout applies it ``T // f`` times, each prediction joining the context of the next.
Frozen noise (the default) starts every chain at 0, so a rollout is a deterministic,
differentiable function of the actions; sampled noise draws the chains' starts.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from contextlib import nullcontext
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.networks.edm import Denoiser, EulerConfig, EulerSampler
from gpc.models.networks.precision import rollout_bf16
from gpc.models.networks.unet2d import InnerUNet
from gpc.models.world_models.config import FEEDBACK, IMAGE_KEY, VisualDynamicsConfig, VisualWorldModelConfig

ACTION_KEY = "action"


def resize_frames(frames: torch.Tensor, size: int) -> torch.Tensor:
    """``(..., C, S0, S0)`` -> ``(..., C, size, size)``: area averaging down, bilinear up."""
    if frames.shape[-1] == size and frames.shape[-2] == size:
        return frames
    lead = frames.shape[:-3]
    flat = frames.reshape((-1,) + tuple(frames.shape[-3:]))
    mode = "area" if frames.shape[-1] > size else "bilinear"
    out = F.interpolate(flat, size=(size, size), mode=mode, **({"align_corners": False} if mode == "bilinear" else {}))
    return out.reshape(lead + out.shape[-3:])


class VisualDynamics(nn.Module):
    """Normaliser (actions) + EDM denoiser around an AdaGroupNorm U-Net + Euler sampler."""

    pixel_centres: torch.Tensor  # registered (non-persistent) buffer

    def __init__(self, config: VisualDynamicsConfig, normalizer: MinMaxNormalizer | None = None) -> None:
        super().__init__()
        self.config = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        inner = InnerUNet(config.unet, config.img_channels, config.context_channels, config.cond_dim)
        self.denoiser = Denoiser(inner, config.edm)
        self.sampler = EulerSampler(self.denoiser, config.sampler)
        s = config.resolution
        lo, hi = config.action_extent
        centres = (torch.arange(s, dtype=torch.float32) + 0.5) / s * (hi - lo) + lo  # pixel centres in action units
        self.register_buffer("pixel_centres", centres, persistent=False)
        self._warned: set[int] = set()
        self.precision = "bf16-auto"  # rollouts' precision (networks.precision.ROLLOUT_PRECISIONS); planners may pin it
        if config.channels_last:  # loading weights copies into these tensors and keeps their layout
            self.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs omit the keyword

    def use_sampler(self, sampler: EulerConfig) -> None:
        """Samples with another Euler chain (e.g. more steps) without retraining: the denoiser is unchanged."""
        self.config = dataclasses.replace(self.config, sampler=sampler)
        self.sampler = EulerSampler(self.denoiser, sampler)

    @property
    def n_obs_steps(self) -> int:
        return self.config.n_obs_steps

    def bf16(self, device_type: str) -> bool:
        """Whether rollouts on ``device_type`` run under bf16 autocast (emulated bf16 is slower than float32)."""
        return rollout_bf16(self.config.bf16, self.precision, device_type)

    def check_normalizer(self) -> None:
        if ACTION_KEY not in self.normalizer.keys():
            raise ValueError("the world model's normaliser has no statistics for action")

    # ------------------------------------------------------------------ frames
    def frames(self, images: torch.Tensor) -> torch.Tensor:
        """Images as stored ``(..., S0, S0, C)``, 0..255, any size -> ``(..., C, S, S)`` in [0, 1].

        A size other than the training stores' (``config.source_size``) is resized with a warning.
        """
        c = self.config
        if images.dim() < 3 or images.shape[-1] != c.img_channels or images.shape[-2] != images.shape[-3]:
            raise ValueError(f"images: expected (..., S, S, {c.img_channels}) as stored, got {tuple(images.shape)}")
        size = int(images.shape[-2])
        if c.source_size is not None and size != c.source_size and size not in self._warned:
            self._warned.add(size)
            warnings.warn(f"frames are {size} px but the world model was trained on {c.source_size} px frames; "
                          f"resizing {size} -> {c.resolution} px", stacklevel=2)
        x = images.float().movedim(-1, -3) / 255.0
        return resize_frames(x, c.resolution)

    def action_maps(self, actions: torch.Tensor) -> torch.Tensor:
        """``(B, f, A)`` raw actions -> ``(B, f, S, S)`` Gaussian blobs at each action's position, in [-1, 1]."""
        sigma = self.config.action_map_sigma
        px = self.pixel_centres.to(actions.dtype)
        gx = torch.exp(-0.5 * ((px - actions[..., 0:1]) / sigma) ** 2)  # (B, f, S) over columns
        gy = torch.exp(-0.5 * ((px - actions[..., 1:2]) / sigma) ** 2)  # (B, f, S) over rows
        return 2.0 * gy[..., :, None] * gx[..., None, :] - 1.0

    def _inputs(self, context: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, H, C, S, S)`` context in [-1, 1], ``(B, f, A)`` raw actions -> (context channels, cond vector)."""
        b = context.shape[0]
        channels = context.reshape(b, -1, *context.shape[-2:])
        if self.config.action_maps:
            channels = torch.cat([channels, self.action_maps(actions).to(channels.dtype)], dim=1)
        cond = self.normalizer.normalize(ACTION_KEY, actions).reshape(b, -1)
        return channels, cond

    # ------------------------------------------------------------------ rollout
    def step(self, context: torch.Tensor, actions: torch.Tensor, noise: str | None = None,
             generator: torch.Generator | None = None) -> torch.Tensor:
        """``(B, H, C, S, S)`` in [-1, 1], ``(B, f, A)`` raw -> ``(B, C, S, S)`` sampled next frame in [-1, 1]."""
        channels, cond = self._inputs(context, actions)
        return self.sampler.sample(tuple(context[:, -1].shape), channels, cond, noise, generator)

    def unroll(self, context: torch.Tensor, actions: torch.Tensor, noise: str | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """``(K, H, C, S, S)`` in [-1, 1], ``(K, N f, A)`` raw -> ``(K, N, C, S, S)`` in [-1, 1]."""
        f = self.config.frameskip
        out = []
        for i in range(actions.shape[1] // f):
            nxt = self.step(context, actions[:, i * f : (i + 1) * f], noise, generator)
            out.append(nxt)
            context = torch.cat([context[:, 1:], nxt[:, None]], dim=1)
        return torch.stack(out, dim=1)

    def _history(self, history: torch.Tensor, k: int) -> torch.Tensor:
        c = self.config
        if history.shape[-1] == c.img_channels and history.shape[-3] != c.img_channels:
            history = self.frames(history)  # images as stored, channel-last 0..255
        want = (c.img_channels, c.resolution, c.resolution)
        if history.dim() == 4:
            history = history.unsqueeze(0).expand(k, *history.shape)
        if history.dim() != 5 or tuple(history.shape[2:]) != want or history.shape[1] < c.n_obs_steps:
            raise ValueError(f"history: expected (K, L >= {c.n_obs_steps}, {', '.join(map(str, want))}) frames in [0, 1] "
                             f"(or (L, ...), or images as stored (..., S0, S0, {c.img_channels})), got {tuple(history.shape)}")
        if history.shape[0] != k:
            raise ValueError(f"history batch {history.shape[0]} differs from actions batch {k}")
        return history[:, history.shape[1] - c.n_obs_steps :: c.frameskip]

    def rollout(self, history: torch.Tensor, actions: torch.Tensor, noise: str | None = None,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Predicted frames for K action chunks, in one batched, differentiable call.

        ``history``: ``(K, L, C, S, S)`` or ``(L, C, S, S)`` frames in [0, 1] at the model's
        resolution (the last ``n_obs_steps`` are read, every ``frameskip``-th of them), or the
        same as stored images ``(..., S0, S0, C)`` 0..255; ``actions``: ``(K, T, A)`` raw.
        Returns ``(K, T // frameskip, C, S, S)`` in [0, 1]: frame ``i`` follows actions
        ``[0, (i + 1) frameskip)`` (trailing actions that do not fill a step are not used).
        ``noise``: ``frozen`` (initial sample 0, deterministic) or ``sampled``; default: the config's.
        """
        c = self.config
        if actions.dim() != 3 or actions.shape[-1] != c.action_dim:
            raise ValueError(f"actions: expected (K, T, {c.action_dim}), got {tuple(actions.shape)}")
        if actions.shape[1] < c.frameskip:
            raise ValueError(f"{actions.shape[1]} actions do not fill one prediction of frameskip {c.frameskip}")
        context = self._history(history, actions.shape[0])
        if not bool(torch.isfinite(context).all()) or not bool(torch.isfinite(actions).all()):
            raise ValueError("history or actions hold NaN or inf")
        use = actions.shape[1] // c.frameskip * c.frameskip
        autocast = torch.autocast(actions.device.type, dtype=torch.bfloat16) if self.bf16(actions.device.type) else nullcontext()
        with autocast:
            frames = self.unroll(context * 2.0 - 1.0, actions[:, :use], noise, generator)
        return ((frames.float() + 1.0) / 2.0).clamp(0.0, 1.0)

    # ------------------------------------------------------------------ loss
    def loss(self, frames: torch.Tensor, actions: torch.Tensor, unroll: int,
             feedback: str = "denoised") -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Denoising loss over a window: ``(B, H + N, C, S, S)`` frames in [-1, 1], ``(B, N f, A)`` raw actions.

        The N predictions are cut into segments of ``unroll`` steps, each started from the
        true context before it. ``unroll = 1`` (phase 1): every prediction from true frames, in
        one batched call. Otherwise (phase 2) each step's context holds the previous steps'
        ``feedback`` frames, detached: ``denoised`` (the one-step estimate of the loss's own
        noisy sample, as the official GPC code does) or ``sampled`` (the sampler's frame).
        Every prediction is supervised; the loss is the mean over steps. With
        ``motion_weight`` > 0, pixels that change between the true previous frame and the
        target weigh more (the agent and the block are a few percent of a frame).
        """
        c, h = self.config, self.config.history
        b, n = frames.shape[0], frames.shape[1] - self.config.history
        if n < 1 or actions.shape[1] != n * c.frameskip or n % unroll:
            raise ValueError(f"window of {frames.shape[1]} frames and {actions.shape[1]} actions does not fit history {h}, "
                             f"frameskip {c.frameskip} and unroll {unroll}")
        if feedback not in FEEDBACK:
            raise ValueError(f"feedback {feedback!r}: use one of {', '.join(FEEDBACK)}")
        acts = actions.reshape(b, n, c.frameskip, -1)
        starts = range(0, n, unroll)
        context = torch.stack([frames[:, j : j + h] for j in starts], dim=1).flatten(0, 1)  # (B * segments, H, ...)
        targets = torch.stack([frames[:, h + j : h + j + unroll] for j in starts], dim=1).flatten(0, 1)
        weights = None
        if c.motion_weight > 0:
            previous = torch.stack([frames[:, h - 1 + j : h - 1 + j + unroll] for j in starts], dim=1).flatten(0, 1)
            weights = 1.0 + c.motion_weight * (targets - previous).abs().mean(dim=2, keepdim=True)  # (B', U, 1, S, S)
            weights = weights / weights.mean(dim=(-2, -1), keepdim=True)
        segment_actions = torch.stack([acts[:, j : j + unroll] for j in starts], dim=1).flatten(0, 1)
        per_step = []
        for i in range(unroll):
            channels, cond = self._inputs(context, segment_actions[:, i])
            err, denoised = self.denoiser.loss(targets[:, i], channels, cond, None if weights is None else weights[:, i])
            per_step.append(err.mean())
            if i + 1 < unroll:
                if feedback == "sampled":
                    with torch.no_grad():
                        fed = self.sampler.sample(tuple(targets[:, i].shape), channels, cond)
                else:
                    fed = denoised.detach().clamp(-1.0, 1.0)
                context = torch.cat([context[:, 1:], fed[:, None]], dim=1)
        steps = torch.stack(per_step)
        loss = steps.mean()
        return loss, {"loss": loss.detach(), "loss_last_step": steps[-1].detach()}

    def distill_loss(self, frames: torch.Tensor, actions: torch.Tensor, teacher: VisualDynamics,
                     action_noise: float) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """This model's sampled frame against ``teacher``'s, every prediction of the window from its true context.

        Frozen noise on both sides: the student learns the teacher's deterministic map from
        (context, actions) to the next frame. Each window's actions move by a Gaussian of a
        random scale up to ``action_noise`` x the action extent (clamped to it), so the student
        also agrees where planners take chunks: off the recorded actions.
        """
        c, h = self.config, self.config.history
        b, n = frames.shape[0], frames.shape[1] - h
        lo, hi = c.action_extent
        scale = torch.rand(b, 1, 1, device=actions.device) * action_noise * (hi - lo)
        moved = (actions + scale * torch.randn_like(actions)).clamp(lo, hi)
        acts = moved.reshape(b, n, c.frameskip, -1).flatten(0, 1)
        context = torch.stack([frames[:, j : j + h] for j in range(n)], dim=1).flatten(0, 1)  # (B N, H, C, S, S)
        with torch.no_grad():
            target = teacher.step(context, acts, "frozen")
        err = (self.step(context, acts, "frozen") - target).pow(2)
        loss = err.mean()
        return loss, {"loss": loss.detach(), "distill_rmse": err.detach().mean(dim=(1, 2, 3)).sqrt().mean()}

    def window_loss(self, batch: Mapping[str, torch.Tensor], config: VisualWorldModelConfig,
                    teacher: VisualDynamics | None = None) -> tuple[torch.Tensor, dict[str, Any]]:
        """A training batch ``{img: (B, W, S0, S0, C) 0..255, action: (B, W, A)}`` -> loss, logs.

        The window's frames are read every ``frameskip`` steps from its first: H context
        frames, then the ``horizon / frameskip`` predictions.
        """
        c, n0 = self.config, config.n_obs_steps
        frames = self.frames(batch[IMAGE_KEY][:, :: c.frameskip]) * 2.0 - 1.0
        actions = batch[ACTION_KEY].float()[:, n0 - 1 : n0 - 1 + config.horizon]
        if teacher is not None:
            return self.distill_loss(frames, actions, teacher, config.distill_action_noise)
        return self.loss(frames, actions, config.unroll_steps, config.feedback)
