"""The policy's pieces against values worked out by hand: noise schedule, samplers, EMA, LR, configs, networks."""

from __future__ import annotations

import math

import pytest
import torch

from gpc.models.networks.ddpm import DiffusionSampler, NoiseConfig, NoiseSchedule, SamplerConfig, squaredcos_betas
from gpc.models.networks.encoders import EncoderConfig, ObsEncoder, crop_images
from gpc.models.networks.resnet import ResNet18Trunk, SpatialSoftmax
from gpc.models.networks.unet1d import ConditionalUnet1D, UNetConfig
from gpc.models.policy.config import PolicyConfig, policy_profile
from gpc.models.training.config_io import from_plain
from gpc.models.training.ema import EMAConfig, EMAWeights
from gpc.models.training.optim import cosine_with_warmup
from gpc.tasks.pusht import LAYOUT

SCHEDULE = NoiseSchedule(NoiseConfig())


def _f(s: float) -> float:
    return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2


def test_squaredcos_schedule_matches_the_closed_form():
    # Uncapped betas telescope: ab[t] = f((t+1)/N) / f(0); only the last beta hits the 0.999 cap.
    ab = SCHEDULE.alpha_bar
    for t in (0, 1, 17, 49, 98):
        assert float(ab[t]) == pytest.approx(_f((t + 1) / 100) / _f(0.0), rel=1e-12)
    assert float(ab[99]) == pytest.approx(float(ab[98]) * (1 - 0.999), rel=1e-12)
    # Literal values computed once by hand (Python floats, product of 1 - beta).
    assert float(ab[0]) == pytest.approx(0.9993687184016583, rel=1e-12)
    assert float(ab[49]) == pytest.approx(0.49384359044063775, rel=1e-12)
    assert float(ab[99]) == pytest.approx(2.4285722793500615e-07, rel=1e-9)
    assert squaredcos_betas(100)[99] == 0.999 and squaredcos_betas(100)[0] == pytest.approx(6.312815983416931e-4)
    assert SCHEDULE.ab(-1) == 1.0


def test_add_noise_is_the_forward_process():
    x0, eps = torch.full((2, 3), 0.5), torch.full((2, 3), -1.0)
    t = torch.tensor([0, 49])
    got = SCHEDULE.add_noise(x0, eps, t)
    for row, step in enumerate((0, 49)):
        a = SCHEDULE.ab(step)
        assert got[row, 0].item() == pytest.approx(math.sqrt(a) * 0.5 - math.sqrt(1 - a), abs=1e-6)


def test_timesteps_use_leading_spacing():
    def steps(method: str, n: int) -> list[int]:
        return DiffusionSampler(SCHEDULE, SamplerConfig(method, n)).timesteps()

    assert steps("ddim", 10) == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    assert steps("ddpm", 100) == list(range(99, -1, -1))
    assert steps("ddim", 30)[:3] == [87, 84, 81] and steps("ddim", 30)[-1] == 0
    with pytest.raises(ValueError, match="exceed"):
        DiffusionSampler(SCHEDULE, SamplerConfig("ddim", 101))
    # "trailing" starts at the last training step (pure noise), which few-step chains need
    assert DiffusionSampler(SCHEDULE, SamplerConfig("ddim", 5, "trailing")).timesteps() == [99, 79, 59, 39, 19]
    assert DiffusionSampler(SCHEDULE, SamplerConfig("ddpm", 100, "trailing")).timesteps() == list(range(99, -1, -1))
    with pytest.raises(ValueError, match="--spacing 'middle'"):
        SamplerConfig("ddim", 5, "middle")


def test_ddpm_step_is_the_posterior_of_ho_et_al():
    sampler = DiffusionSampler(SCHEDULE, SamplerConfig("ddpm", 100))
    x, eps, t = torch.tensor([0.3, -0.2]), torch.tensor([0.1, 0.05]), 50
    a_t, a_p = SCHEDULE.ab(t), SCHEDULE.ab(t - 1)
    alpha, beta = a_t / a_p, 1 - a_t / a_p
    # Ho et al. eq. 11 (eps form), equal to the x0 form while the clip does not bind.
    mean = (x - beta / math.sqrt(1 - a_t) * eps) / math.sqrt(alpha)
    sigma = math.sqrt((1 - a_p) / (1 - a_t) * beta)
    assert torch.allclose(sampler.step(x, eps, t, None), mean, atol=1e-6)
    assert torch.allclose(sampler.step(x, eps, t, lambda: torch.ones(2)), mean + sigma, atol=1e-6)
    # At t = 0 the step returns the (clipped) clean estimate and draws no noise.
    assert torch.allclose(sampler.step(x, eps, 0, lambda: 1 / 0), (x - math.sqrt(1 - SCHEDULE.ab(0)) * eps) / math.sqrt(SCHEDULE.ab(0)))


def test_ddim_step_and_clipping():
    sampler = DiffusionSampler(SCHEDULE, SamplerConfig("ddim", 10))
    x, eps, t = torch.tensor([0.3]), torch.tensor([0.1]), 50
    a_t, a_p = SCHEDULE.ab(50), SCHEDULE.ab(40)
    x0 = (0.3 - math.sqrt(1 - a_t) * 0.1) / math.sqrt(a_t)
    assert sampler.step(x, eps, t, None).item() == pytest.approx(math.sqrt(a_p) * x0 + math.sqrt(1 - a_p) * 0.1, abs=1e-6)
    # A clean estimate outside [-1, 1] is clipped before it is used.
    big = sampler.step(torch.tensor([3.0]), torch.tensor([0.0]), 0, None)
    assert big.item() == pytest.approx(1.0)


@pytest.mark.parametrize("method,steps,spacing", [("ddim", 10, "leading"), ("ddpm", 100, "leading"), ("ddim", 1, "leading"),
                                                  ("ddim", 5, "trailing"), ("ddpm", 10, "trailing")])
def test_an_oracle_denoiser_recovers_the_clean_sample(method, steps, spacing):
    x0 = torch.tensor([[0.7, -0.4, 0.0, 0.95]])
    sampler = DiffusionSampler(SCHEDULE, SamplerConfig(method, steps, spacing))

    def oracle(x, t):  # the exact noise separating x from x0 at step t
        return (x - math.sqrt(SCHEDULE.ab(t)) * x0) / math.sqrt(1 - SCHEDULE.ab(t))

    g = torch.Generator().manual_seed(0)
    out = sampler.sample(oracle, torch.randn(x0.shape, generator=g), lambda: torch.randn(x0.shape, generator=g))
    assert torch.allclose(out, x0, atol=1e-4)


def test_ema_decay_warms_up_like_diffusion_policy():
    cfg = EMAConfig()
    assert cfg.decay(0) == 0.0 and cfg.decay(1) == 0.0
    assert cfg.decay(2) == pytest.approx(1 - 2 ** -0.75)
    assert cfg.decay(10_001) == pytest.approx(1 - 10_001 ** -0.75)
    assert cfg.decay(10**9) == 0.9999
    net = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        net.weight.fill_(1.0)
    ema = EMAWeights(net, cfg)
    with torch.no_grad():
        net.weight.fill_(3.0)
    assert ema.update(net) == 0.0 and ema.model.weight.item() == 3.0  # the first update copies
    ema.update(net)
    with torch.no_grad():
        net.weight.fill_(5.0)
    d = ema.update(net)  # third update: decay(2)
    assert ema.model.weight.item() == pytest.approx(d * 3.0 + (1 - d) * 5.0)
    assert int(ema.updates) == 3 and not ema.model.weight.requires_grad
    ema.train()
    assert not ema.model.training


def test_cosine_schedule_with_warmup():
    f = cosine_with_warmup(10, 110)
    assert f(0) == 0.0 and f(5) == 0.5 and f(10) == 1.0
    assert f(60) == pytest.approx(0.5) and f(110) == pytest.approx(0.0) and f(200) == 0.0


def test_configs_round_trip_and_validate():
    cfg = policy_profile("cpu", "keypoints", LAYOUT).config.with_obs_shapes({"keypoint": (9, 2), "state": (5,)})
    plain = cfg.to_dict()
    assert PolicyConfig.from_dict(plain) == cfg
    listed = {**plain, "unet": {**plain["unet"], "down_dims": [64, 128, 256]}}
    assert PolicyConfig.from_dict(listed).unet.down_dims == (64, 128, 256)
    with pytest.raises(ValueError, match="unknown field"):
        from_plain(UNetConfig, {"widths": (1,)})
    with pytest.raises(ValueError, match="multiple of 4"):
        PolicyConfig(task="pusht", action_dim=2, horizon=10)
    with pytest.raises(ValueError, match="obs type"):
        EncoderConfig("lidar")
    with pytest.raises(ValueError, match="n_groups"):
        UNetConfig(down_dims=(12, 24))
    with pytest.raises(ValueError, match="profile"):
        policy_profile("huge", "state", LAYOUT)
    with pytest.raises(ValueError, match="needs data key"):
        PolicyConfig(task="pusht", action_dim=2).with_obs_shapes({"keypoint": (9, 2)})


def test_unet_has_diffusion_policys_size_and_shapes():
    # Diffusion Policy's keypoint Push-T network: 65.8M parameters (GUIDE: ~65M).
    with torch.device("meta"):
        paper = ConditionalUnet1D(UNetConfig(), input_dim=2, global_cond_dim=40)
    assert sum(p.numel() for p in paper.parameters()) == pytest.approx(65.78e6, rel=1e-3)
    net = ConditionalUnet1D(UNetConfig(down_dims=(16, 32, 64), step_embed_dim=16), input_dim=2, global_cond_dim=6)
    out = net(torch.randn(3, 16, 2), torch.tensor([0, 5, 99]), torch.randn(3, 6))
    assert out.shape == (3, 16, 2)
    # A scalar step broadcasts over the batch; batch size changes results only by float rounding.
    assert torch.allclose(net(torch.zeros(2, 16, 2), torch.tensor(7), torch.zeros(2, 6))[0],
                          net(torch.zeros(1, 16, 2), torch.tensor([7]), torch.zeros(1, 6))[0], atol=1e-5)


def test_resnet_spatial_softmax_and_crops():
    trunk = ResNet18Trunk(3, width=64)
    assert sum(p.numel() for p in trunk.parameters()) == pytest.approx(11.17e6, rel=1e-2)  # ResNet18 without its classifier
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in trunk.modules())
    pool = SpatialSoftmax(1, 1)
    with torch.no_grad():
        pool.to_maps.weight.fill_(1.0)
        pool.to_maps.bias.zero_()
    peak = torch.full((1, 1, 3, 3), -50.0)
    peak[0, 0, 0, 2] = 50.0  # top-right corner
    assert torch.allclose(pool(peak), torch.tensor([[1.0, -1.0]]), atol=1e-6)
    images = torch.arange(2 * 6 * 6 * 1, dtype=torch.float32).reshape(2, 6, 6, 1)
    assert torch.equal(crop_images(images, 4, random=False), images[:, 1:5, 1:5])
    torch.manual_seed(0)
    crops = crop_images(images, 4, random=True)
    for i in range(2):  # each random crop is some 4x4 window of its own image
        top, left = divmod(int(crops[i, 0, 0, 0] - images[i, 0, 0, 0]), 6)
        assert torch.equal(crops[i], images[i, top : top + 4, left : left + 4])


def test_encoders_share_one_interface():
    shapes = (("state", (5,)), ("keypoint", (9, 2)), ("img", (16, 16, 3)))
    dims = {}
    for obs in ("state", "keypoints", "image"):
        enc = ObsEncoder(EncoderConfig(obs, shapes, crop_size=12, resnet_width=8, spatial_keypoints=4, image_feature_dim=8))
        batch = {"state": torch.zeros(2, 2, 5), "keypoint": torch.zeros(2, 2, 9, 2), "img": torch.zeros(2, 2, 16, 16, 3)}
        assert enc(batch).shape == (2, 2, enc.feature_dim)
        dims[obs] = enc.feature_dim
    assert dims == {"state": 5, "keypoints": 20, "image": 10}


def test_an_observation_mlp_forms_features_that_depend_on_goal_and_state_together():
    shapes = (("state", (3,)), ("goal", (2,)))
    plain = ObsEncoder(EncoderConfig("state", shapes, goal=True))
    assert plain.feature_dim == 5 and not list(plain.parameters())  # Diffusion Policy's: the features as read
    torch.manual_seed(0)
    enc = ObsEncoder(EncoderConfig("state", shapes, goal=True, mlp=(16, 8)))
    assert enc.feature_dim == 8 and [type(m).__name__ for m in enc.mlp] == ["Linear", "Mish", "Linear"]

    def features(state: float, goal: float) -> torch.Tensor:
        return enc({"state": torch.full((1, 1, 3), state), "goal": torch.full((1, 1, 2), goal)})[0, 0]

    # Not additive in state and goal (a plain linear map of the joined features would be): the interaction the
    # U-Net's per-block linear FiLM maps cannot form by themselves.
    interaction = features(1.0, 1.0) - features(1.0, -1.0) - features(-1.0, 1.0) + features(-1.0, -1.0)
    assert interaction.abs().max() > 1e-3
    # Checkpoints written before the option load as they were: no MLP.
    cfg = policy_profile("cpu", "state", LAYOUT, mlp=(32,)).config
    assert cfg.encoder.mlp == (32,)
    legacy = cfg.to_dict()
    del legacy["encoder"]["mlp"]
    assert PolicyConfig.from_dict(legacy).encoder.mlp == ()
    with pytest.raises(ValueError, match="mlp widths"):
        EncoderConfig("state", mlp=(0,))
