"""EDM diffusion for a conditional image predictor, split as DIAMOND splits it.

- ``EDMConfig``: the training noise process (Karras et al. 2022 preconditioning, DIAMOND's constants);
- ``Denoiser``: wraps an inner network (any ``nn.Module`` called as
  ``inner(noisy_in, c_noise, context, cond)``) with the preconditioning
  ``D(x, sigma) = c_skip x + c_out F(c_in x, c_noise)`` and its loss;
- ``EulerSampler``: a plain class (not a module) configured by ``EulerConfig`` that draws a
  sample with a few Euler steps over Karras' sigma schedule, either from sampled noise or
  from *frozen* noise (initial sample 0), which makes it a deterministic, differentiable
  function of its conditioning.

This is a different process from the policy's DDPM/DDIM (``gpc.models.networks.ddpm``): continuous
sigmas, x0-style preconditioning, no discrete timesteps.

Preconditioning (``sigma`` includes the offset noise, as DIAMOND's ``compute_conditioners``)::

    s = sqrt(sigma^2 + offset^2)
    c_in = 1 / sqrt(s^2 + sd^2)    c_skip = sd^2 / (s^2 + sd^2)    c_out = s sqrt(c_skip)    c_noise = log(s) / 4

Training draws ``log sigma ~ N(loc, scale)`` clipped to ``[sigma_min, sigma_max]``, noises the
target as ``x + offset * n_channel + sigma * n`` and regresses ``F`` onto
``(x - c_skip x_noisy) / c_out`` (unit-variance targets at every noise level).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

NOISE_MODES = ("frozen", "sampled")


@dataclass(frozen=True)
class EDMConfig:
    """The EDM training process (defaults: DIAMOND's, as the official GPC code uses them)."""

    sigma_data: float = 0.5  # standard deviation of the (scaled to [-1, 1]) frames
    sigma_offset_noise: float = 0.1  # per-channel constant noise added in training (DIAMOND Atari: 0.3)
    loc: float = -1.2  # mean of log sigma in training
    scale: float = 1.2  # standard deviation of log sigma in training
    sigma_min: float = 2e-3  # training sigmas are clipped to [sigma_min, sigma_max]
    sigma_max: float = 20.0

    def __post_init__(self) -> None:
        if self.sigma_data <= 0 or self.sigma_offset_noise < 0 or self.scale < 0:
            raise ValueError("EDM: sigma_data must be > 0, sigma_offset_noise and scale >= 0")
        if not 0 < self.sigma_min < self.sigma_max:
            raise ValueError(f"EDM training sigmas [{self.sigma_min}, {self.sigma_max}]: need 0 < min < max")


@dataclass(frozen=True)
class EulerConfig:
    """The inference chain: ``steps`` Euler steps over Karras' schedule (DIAMOND's sampler, order 1, no churn)."""

    steps: int = 3  # denoising steps per predicted frame
    sigma_min: float = 2e-3  # last non-zero sigma of the schedule
    sigma_max: float = 5.0  # first sigma of the schedule
    rho: float = 7.0  # schedule curvature
    noise: str = "frozen"  # default initial sample: frozen (0, deterministic) or sampled (unit Gaussian, as DIAMOND)

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"sampler steps {self.steps}: must be at least 1")
        if not 0 < self.sigma_min < self.sigma_max or self.rho <= 0:
            raise ValueError(f"sampler sigmas [{self.sigma_min}, {self.sigma_max}], rho {self.rho}: need 0 < min < max, rho > 0")
        if self.noise not in NOISE_MODES:
            raise ValueError(f"sampler noise {self.noise!r}: use one of {', '.join(NOISE_MODES)}")


def karras_sigmas(steps: int, sigma_min: float, sigma_max: float, rho: float) -> torch.Tensor:
    """``steps`` sigmas from ``sigma_max`` down to ``sigma_min`` (Karras et al. eq. 5), then a final 0."""
    ramp = torch.linspace(0, 1, steps, dtype=torch.float64)
    lo, hi = sigma_min ** (1 / rho), sigma_max ** (1 / rho)
    sigmas = (hi + ramp * (lo - hi)) ** rho
    return torch.cat([sigmas, sigmas.new_zeros(1)]).float()


def _bcast(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``(B,)`` -> ``(B, 1, ..., 1)`` broadcastable against ``like``."""
    return x.reshape(x.shape + (1,) * (like.dim() - x.dim()))


@dataclass
class Conditioners:
    """The EDM preconditioning coefficients for one batch of sigmas, each ``(B,)``."""

    c_in: torch.Tensor
    c_out: torch.Tensor
    c_skip: torch.Tensor
    c_noise: torch.Tensor


class Denoiser(nn.Module):
    """EDM preconditioning around ``inner``: the denoised estimate and the training loss.

    ``context`` (conditioning frames, e.g. ``(B, H * C, S, S)`` in [-1, 1]) is rescaled by
    ``1 / sigma_data`` before it enters ``inner``; ``cond`` (e.g. the normalised actions) is passed as is.
    Unlike DIAMOND's, ``denoise`` keeps gradients and does not quantise its output, so a
    planner can differentiate a rollout with respect to the actions.
    """

    def __init__(self, inner: nn.Module, config: EDMConfig) -> None:
        super().__init__()
        self.inner = inner
        self.config = config

    def conditioners(self, sigma: torch.Tensor) -> Conditioners:
        sd = self.config.sigma_data
        s = (sigma.pow(2) + self.config.sigma_offset_noise ** 2).sqrt()
        c_in = (s.pow(2) + sd * sd).rsqrt()
        c_skip = sd * sd / (s.pow(2) + sd * sd)
        return Conditioners(c_in=c_in, c_out=s * c_skip.sqrt(), c_skip=c_skip, c_noise=s.log() / 4)

    def _output(self, noisy: torch.Tensor, cs: Conditioners, context: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return self.inner(noisy * _bcast(cs.c_in, noisy), cs.c_noise, context / self.config.sigma_data, cond)

    def denoise(self, noisy: torch.Tensor, sigma: torch.Tensor, context: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """``(B, C, S, S)`` noisy frames at ``sigma`` (``(B,)`` or scalar) -> ``(B, C, S, S)`` denoised estimate."""
        sigma = torch.as_tensor(sigma, dtype=noisy.dtype, device=noisy.device).expand(noisy.shape[0])
        cs = self.conditioners(sigma)
        out = self._output(noisy, cs, context, cond)
        return _bcast(cs.c_skip, noisy) * noisy + _bcast(cs.c_out, noisy) * out

    def sample_sigma(self, n: int, device: torch.device) -> torch.Tensor:
        c = self.config
        return (torch.randn(n, device=device) * c.scale + c.loc).exp().clamp(c.sigma_min, c.sigma_max)

    def loss(self, target: torch.Tensor, context: torch.Tensor, cond: torch.Tensor,
             weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One denoising step at random sigmas -> (per-sample mean squared error ``(B,)``, denoised estimate).

        ``target``: ``(B, C, S, S)`` clean next frames in [-1, 1]; ``weight``: optional per-pixel
        weights broadcastable to it (e.g. ``(B, 1, S, S)``, mean 1). The denoised estimate is
        what the official GPC code feeds back (detached) as context when it unrolls.
        """
        b = target.shape[0]
        sigma = self.sample_sigma(b, target.device)
        offset = self.config.sigma_offset_noise * torch.randn(b, target.shape[1], 1, 1, device=target.device)
        noisy = target + offset + _bcast(sigma, target) * torch.randn_like(target)
        cs = self.conditioners(sigma)
        out = self._output(noisy, cs, context, cond)
        c_skip, c_out = _bcast(cs.c_skip, target), _bcast(cs.c_out, target)
        err = (out - (target - c_skip * noisy) / c_out).pow(2)
        per_sample = (err if weight is None else err * weight).flatten(1).mean(dim=1)
        return per_sample, c_skip * noisy + c_out * out


class EulerSampler:
    """Draws ``x`` given ``(context, cond)`` with Euler steps over ``karras_sigmas``; differentiable.

    ``noise="frozen"`` starts every chain at 0 (deterministic: the same inputs give the same
    frame, and gradients with respect to ``cond`` are stable); ``"sampled"`` starts it at a unit
    Gaussian, as DIAMOND does (not scaled by ``sigma_max``).
    """

    def __init__(self, denoiser: Denoiser, config: EulerConfig) -> None:
        self.denoiser = denoiser
        self.config = config
        self.sigmas = karras_sigmas(config.steps, config.sigma_min, config.sigma_max, config.rho).tolist()

    def initial(self, shape: tuple[int, ...], like: torch.Tensor, noise: str | None = None,
                generator: torch.Generator | None = None) -> torch.Tensor:
        mode = noise or self.config.noise
        if mode not in NOISE_MODES:
            raise ValueError(f"noise {mode!r}: use one of {', '.join(NOISE_MODES)}")
        if mode == "frozen":
            return like.new_zeros(shape)
        return torch.randn(shape, generator=generator, device=like.device, dtype=like.dtype)

    def sample(self, shape: tuple[int, ...], context: torch.Tensor, cond: torch.Tensor, noise: str | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """``shape = (B, C, S, S)`` of the frames to draw; ``context``, ``cond`` as ``Denoiser.denoise`` takes them."""
        x = self.initial(shape, context, noise, generator)
        for sigma, nxt in zip(self.sigmas[:-1], self.sigmas[1:]):
            denoised = self.denoiser.denoise(x, torch.tensor(sigma, device=x.device), context, cond)
            x = x + (x - denoised) * ((nxt - sigma) / sigma)
        return x
