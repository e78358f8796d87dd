"""DDPM noise schedule and DDPM / DDIM samplers, as Diffusion Policy and LeRobot use them.

We write the ~100 lines ourselves rather than add ``diffusers``: that package would bring a
hub client and a dozen transitive dependencies for two update rules, and its schedulers
keep per-call state (``set_timesteps``) that is awkward to share between a trained module
and concurrent samplers. The formulas follow diffusers' conventions exactly, so a policy
behaves as Diffusion Policy's (``DDPMScheduler`` / ``DDIMScheduler`` with
``squaredcos_cap_v2``, ``linear`` or ``scaled_linear`` betas, ``fixed_small`` variance,
``clip_sample``, ``set_alpha_to_one``, "leading" timestep spacing, eta 0, epsilon or sample
prediction); ``tests/test_policy_diffusion.py`` checks them against reference values computed
by hand, ``tests/test_foreign_policies.py`` against LeRobot's and Diffusion Policy's own
sampling. Coefficients are computed in float64.

Notation: ``ab[t]`` is the cumulative product of ``1 - beta`` up to step ``t`` (diffusers'
``alphas_cumprod``); ``ab[-1] = 1``. Training noises ``x0`` to
``x_t = sqrt(ab[t]) x0 + sqrt(1 - ab[t]) eps`` and the network predicts ``eps`` (``epsilon``,
gpc's choice) or ``x0`` itself (``sample``); either way a step reads both estimates, the noise
one computed from the unclipped ``x0`` as diffusers does.
A chain of ``S`` steps visits ``t = (S-1) r, ..., r, 0`` with ``r = N // S`` ("leading"
spacing, diffusers' default and Diffusion Policy's) or ``t = N - 1, N - 1 - r, ..., r - 1``
("trailing": the first step starts from pure noise, which few-step chains need) and steps
from ``t`` to the next visited ``p`` (``-1`` after the last):

- DDPM: ``x_p = c0 x0_hat + ct x_t + sigma z`` (posterior mean plus ``fixed_small`` noise, none at t = 0),
- DDIM (eta 0): ``x_p = sqrt(ab[p]) x0_hat + sqrt(1 - ab[p]) eps_hat`` (deterministic),

where ``x0_hat`` is clipped to ``[-clip, clip]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

BETA_SCHEDULES = ("squaredcos_cap_v2", "linear", "scaled_linear")
PREDICTIONS = ("epsilon", "sample")
SAMPLERS = ("ddpm", "ddim")
SPACINGS = ("leading", "trailing")


@dataclass(frozen=True)
class NoiseConfig:
    """The training noise process."""

    train_steps: int = 100  # diffusion steps N (Diffusion Policy: 100)
    beta_schedule: str = "squaredcos_cap_v2"  # cosine schedule of Nichol & Dhariwal, betas capped at max_beta
    max_beta: float = 0.999  # cap on each beta
    clip_sample: float = 1.0  # clip predicted clean samples to [-clip, clip]; 0 disables clipping
    prediction: str = "epsilon"  # what the network predicts: the noise (epsilon) or the clean chunk (sample)
    beta_start: float = 1e-4  # first beta of the linear and scaled_linear schedules
    beta_end: float = 0.02  # last beta of the linear and scaled_linear schedules

    def __post_init__(self) -> None:
        if self.train_steps < 1:
            raise ValueError(f"train_steps {self.train_steps}: must be at least 1")
        if self.beta_schedule not in BETA_SCHEDULES:
            raise ValueError(f"beta_schedule {self.beta_schedule!r}: use one of {', '.join(BETA_SCHEDULES)}")
        if not 0 < self.max_beta < 1:
            raise ValueError(f"max_beta {self.max_beta}: must lie in (0, 1)")
        if self.clip_sample < 0:
            raise ValueError(f"clip_sample {self.clip_sample}: must be >= 0 (0 disables clipping)")
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"prediction {self.prediction!r}: use one of {', '.join(PREDICTIONS)}")
        if not 0 < self.beta_start <= self.beta_end < 1:
            raise ValueError(f"betas ({self.beta_start}, {self.beta_end}): need 0 < beta_start <= beta_end < 1")


@dataclass(frozen=True)
class SamplerConfig:
    """How samples are drawn at inference."""

    method: str = "ddim"  # ddim (deterministic, few steps; CPU default) or ddpm (stochastic full chain)
    steps: int = 10  # denoising steps; at most NoiseConfig.train_steps (ddpm normally uses all of them)
    spacing: str = "leading"  # which training steps a short chain visits (see the module docstring)

    def __post_init__(self) -> None:
        if self.method not in SAMPLERS:
            raise ValueError(f"sampler {self.method!r}: use one of {', '.join(SAMPLERS)}")
        if self.spacing not in SPACINGS:
            raise ValueError(f"--spacing {self.spacing!r}: use one of {', '.join(SPACINGS)}")
        if self.steps < 1:
            raise ValueError(f"sampler steps {self.steps}: must be at least 1")


def squaredcos_betas(n: int, max_beta: float = 0.999) -> list[float]:
    """``beta_i = min(1 - f((i+1)/n) / f(i/n), max_beta)`` with ``f(s) = cos((s + 0.008) / 1.008 * pi/2)^2``."""
    f = lambda s: math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    return [min(1 - f((i + 1) / n) / f(i / n), max_beta) for i in range(n)]


def betas(config: NoiseConfig) -> torch.Tensor:
    """The schedule's ``N`` betas in float64 (``scaled_linear``: linear in ``sqrt(beta)``, as diffusers)."""
    n = config.train_steps
    if config.beta_schedule == "linear":
        return torch.linspace(config.beta_start, config.beta_end, n, dtype=torch.float64)
    if config.beta_schedule == "scaled_linear":
        return torch.linspace(config.beta_start**0.5, config.beta_end**0.5, n, dtype=torch.float64) ** 2
    return torch.tensor(squaredcos_betas(n, config.max_beta), dtype=torch.float64)


class NoiseSchedule:
    """Cumulative signal levels ``ab[t]`` and the forward (noising) process."""

    def __init__(self, config: NoiseConfig) -> None:
        self.config = config
        self.alpha_bar = torch.cumprod(1.0 - betas(config), dim=0)  # float64, CPU

    @property
    def train_steps(self) -> int:
        return self.config.train_steps

    def ab(self, t: int) -> float:
        """``ab[t]`` as a Python float, with ``ab[t] = 1`` for ``t < 0``."""
        return 1.0 if t < 0 else float(self.alpha_bar[t])

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``x0, noise (B, ...)``, integer ``t (B,)`` -> ``x_t (B, ...)``."""
        ab = self.alpha_bar.to(torch.float32).to(x0.device)[t].to(x0.dtype).reshape((-1,) + (1,) * (x0.dim() - 1))
        return ab.sqrt() * x0 + (1.0 - ab).sqrt() * noise

    def estimates(self, x: torch.Tensor, out: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The network's output at ``x_t`` -> (clean chunk, clipped; noise, from the unclipped chunk)."""
        ab = self.ab(t)
        if self.config.prediction == "sample":
            x0, eps = out, (x - math.sqrt(ab) * out) / math.sqrt(1.0 - ab)
        else:
            x0, eps = (x - math.sqrt(1.0 - ab) * out) / math.sqrt(ab), out
        clip = self.config.clip_sample
        return (x0.clamp(-clip, clip) if clip > 0 else x0), eps

    def target(self, x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """What the network learns to output for ``x_t`` made from ``x0`` and ``noise``."""
        return x0 if self.config.prediction == "sample" else noise


Denoise = Callable[[torch.Tensor, int], torch.Tensor]  # (x_t, t) -> the network's output (eps or x0), same shape
DrawNoise = Callable[[], torch.Tensor]  # -> a standard normal tensor shaped like the sample


class DiffusionSampler:
    """Runs a DDPM or DDIM chain from given initial noise; stateless between calls."""

    def __init__(self, schedule: NoiseSchedule, config: SamplerConfig) -> None:
        if config.steps > schedule.train_steps:
            raise ValueError(f"sampler steps {config.steps} exceed the {schedule.train_steps} training steps")
        self.schedule, self.config = schedule, config
        self.stride = schedule.train_steps // config.steps

    def timesteps(self) -> list[int]:
        """Steps visited, first to last."""
        if self.config.spacing == "trailing":
            n, k = self.schedule.train_steps, self.config.steps
            return [round(n - i * n / k) - 1 for i in range(k)]
        return [i * self.stride for i in range(self.config.steps)][::-1]

    def step(self, x: torch.Tensor, out: torch.Tensor, t: int, noise: DrawNoise | None,
             prev: int | None = None) -> torch.Tensor:
        """One update from ``x_t`` to ``x_prev`` (default ``t - stride``) given the network's output;
        ``noise`` is drawn only by DDPM at t > 0."""
        s = self.schedule
        prev = t - self.stride if prev is None else prev
        ab_t, ab_p = s.ab(t), s.ab(prev)
        x0, eps = s.estimates(x, out, t)
        if self.config.method == "ddim":
            return math.sqrt(ab_p) * x0 + math.sqrt(1.0 - ab_p) * eps
        alpha = ab_t / ab_p
        beta = 1.0 - alpha
        mean = (math.sqrt(ab_p) * beta / (1.0 - ab_t)) * x0 + (math.sqrt(alpha) * (1.0 - ab_p) / (1.0 - ab_t)) * x
        if prev < 0 or noise is None:
            return mean
        variance = max((1.0 - ab_p) / (1.0 - ab_t) * beta, 1e-20)
        return mean + math.sqrt(variance) * noise()

    def sample(self, denoise: Denoise, x: torch.Tensor, noise: DrawNoise) -> torch.Tensor:
        """Denoise initial noise ``x`` through the whole chain and return the final sample."""
        steps = self.timesteps()
        for t, prev in zip(steps, steps[1:] + [-1]):
            x = self.step(x, denoise(x, t), t, noise, prev)
        return x
