"""Our DDPM / DDIM schedule and update rule against Hugging Face ``diffusers`` (a dev dependency), to 1e-6.

Diffusion Policy and LeRobot sample with ``DDPMScheduler`` / ``DDIMScheduler`` (``squaredcos_cap_v2``
betas by default, epsilon prediction by default, ``fixed_small`` variance, ``clip_sample``,
``set_alpha_to_one``, "leading" steps); ``gpc.models.networks.ddpm`` writes the same formulas itself,
checked here step by step, also for the other schedules and sample prediction a LeRobot config may name.
"""

from __future__ import annotations

import pytest
import torch

from gpc.models.networks.ddpm import DiffusionSampler, NoiseConfig, NoiseSchedule, SamplerConfig, betas

diffusers = pytest.importorskip("diffusers", reason="diffusers is a dev dependency (pip install -e '.[dev]')")

N = 100
SCHEDULE = NoiseSchedule(NoiseConfig(train_steps=N))


def reference(method: str, steps: int, spacing: str = "leading", config: NoiseConfig = NoiseConfig(train_steps=N)):
    kw = dict(num_train_timesteps=N, beta_schedule=config.beta_schedule, clip_sample=config.clip_sample > 0,
              clip_sample_range=config.clip_sample or 1.0, prediction_type=config.prediction, timestep_spacing=spacing,
              beta_start=config.beta_start, beta_end=config.beta_end)
    if method == "ddpm":
        sched = diffusers.DDPMScheduler(variance_type="fixed_small", **kw)
    else:
        sched = diffusers.DDIMScheduler(set_alpha_to_one=True, **kw)
    sched.set_timesteps(steps)
    return sched


def in_float64(sched, config: NoiseConfig):
    """diffusers computes its betas in float32 (that rounding alone moves a chain by ~1e-6); comparing update
    rules, both run on the same float64 betas (the schedules themselves are compared above)."""
    sched.betas = betas(config)
    sched.alphas = 1.0 - sched.betas
    sched.alphas_cumprod = torch.cumprod(sched.alphas, dim=0)
    if hasattr(sched, "final_alpha_cumprod"):
        sched.final_alpha_cumprod = torch.tensor(1.0, dtype=torch.float64)
    return sched


@pytest.mark.parametrize("schedule", ["squaredcos_cap_v2", "linear", "scaled_linear"])
def test_alphas_cumprod_equal_diffusers(schedule):
    config = NoiseConfig(train_steps=N, beta_schedule=schedule)
    ours = NoiseSchedule(config).alpha_bar
    theirs = reference("ddpm", N, config=config).alphas_cumprod.double()
    assert torch.allclose(ours, theirs, atol=1e-6, rtol=0)


@pytest.mark.parametrize("method,steps,spacing", [("ddim", 10, "leading"), ("ddim", 16, "leading"), ("ddpm", 100, "leading"),
                                                  ("ddim", 5, "trailing"), ("ddpm", 10, "leading")])
def test_timesteps_equal_diffusers(method, steps, spacing):
    ours = DiffusionSampler(SCHEDULE, SamplerConfig(method, steps, spacing)).timesteps()
    assert ours == reference(method, steps, spacing).timesteps.tolist()


@pytest.mark.parametrize("method,steps,spacing", [("ddim", 10, "leading"), ("ddim", 5, "trailing"), ("ddpm", 100, "leading"),
                                                  ("ddpm", 10, "leading")])
@pytest.mark.parametrize("noise", [NoiseConfig(train_steps=N),
                                   NoiseConfig(train_steps=N, prediction="sample"),
                                   NoiseConfig(train_steps=N, beta_schedule="linear", beta_start=1e-4, beta_end=0.02),
                                   NoiseConfig(train_steps=N, beta_schedule="scaled_linear", beta_start=1e-4, beta_end=0.02,
                                               prediction="sample", clip_sample=0.5)],
                         ids=["epsilon", "sample", "linear", "scaled-linear-sample-clip0.5"])
def test_every_update_equals_diffusers(method, steps, spacing, noise):
    """A whole chain with a fixed pseudo-denoiser: each step's output agrees with diffusers' ``step`` to 1e-9."""
    sampler = DiffusionSampler(NoiseSchedule(noise), SamplerConfig(method, steps, spacing))
    sched = in_float64(reference(method, steps, spacing, noise), noise)
    x = torch.randn(4, 16, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    ours_g, theirs_g = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)  # DDPM's noise: one stream each
    timesteps = sampler.timesteps()
    for i, t in enumerate(timesteps):
        eps = torch.tanh(x * 0.7 + 0.1 * t / N)  # any smooth function of (x, t) will do
        prev = timesteps[i + 1] if i + 1 < len(timesteps) else -1
        ours = sampler.step(x, eps, t, lambda: torch.randn(x.shape, generator=ours_g, dtype=torch.float64), prev)
        kwargs = {"generator": theirs_g} if method == "ddpm" else {"eta": 0.0}
        theirs = sched.step(eps, t, x, **kwargs).prev_sample
        assert torch.allclose(ours, theirs.to(ours.dtype), atol=1e-9, rtol=0), (method, t)
        x = ours
