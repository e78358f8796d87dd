"""The learned image reward: tiny training on rendered frames, checkpoints, gradients, the reward, the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gpc.cli.reward import reward_app
from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore
from gpc.models.rewards.learned import (
    ImageReward,
    RewardPredictorConfig,
    RewardPredictorModule,
    random_blur,
    random_shift,
    reward_profile,
)
from gpc.models.rewards.learned_eval import evaluate_reward_predictor
from gpc.models.rewards.registration import RegistrationReward, Reward, RewardConfig
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.tasks.pusht import LAYOUT, geometry
from gpc.tasks.pusht.render import draw_scene, draw_state

GOAL = torch.tensor(geometry.GOAL_POSE, dtype=torch.float32)


def make_store(path: Path, episodes: int = 6, length: int = 12, seed: int = 0) -> Path:
    """Rendered 96 px frames of a block drifting and turning (angles cross 0 / 2 pi), agent beside it."""
    rng = np.random.default_rng(seed)
    store = EpisodeStore.create(path, {"task": "pusht"})
    for e in range(episodes):
        block, th = rng.uniform(150, 350, 2), rng.uniform(-1, 1)
        velocity, spin = rng.uniform(-8, 8, 2), rng.uniform(-0.1, 0.1)
        states = []
        for t in range(length):
            b = block + t * velocity
            states.append([*(b + [0.0, -90.0]), *b, (th + t * spin) % (2 * np.pi)])
        state = np.array(states, np.float32)
        img = np.stack([draw_state(s) for s in state])
        store.append_episode({"img": img, "state": state, "action": state[:, :2].copy()}, seed=e)
    return path


def tiny(**kw) -> RewardPredictorConfig:
    config = reward_profile("tiny", LAYOUT).config
    return dataclasses.replace(config, **kw)


def run(tmp: Path, name: str, **kw) -> RunConfig:
    kw = {"max_steps": 30, "batch_size": 16, "progress": False, "accelerator": "cpu", "val_ratio": 0.34, "val_every": 15, **kw}
    return RunConfig(run_dir=tmp / name, **kw)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return make_store(tmp_path_factory.mktemp("data") / "frames.zarr")


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    return train(RewardPredictorModule, tiny(), [store], run(tmp_path_factory.mktemp("runs"), "reward"))


def _frames(store: Path, episode: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    ep = EpisodeStore.open(store).episode(episode, ["img", "state"])
    return torch.from_numpy(ep["img"]).permute(0, 3, 1, 2).float() / 255.0, torch.from_numpy(ep["state"])


def test_training_lowers_the_loss_and_logs_registration_errors(trained, store):
    module = trained.module
    frames, states = _frames(store)
    torch.manual_seed(0)
    fresh = RewardPredictorModule(module.config, normalizer=module.predictor.normalizer)

    def loss(m: RewardPredictorModule) -> float:
        with torch.no_grad():
            p = m.predictor
            return float(torch.nn.functional.mse_loss(p.raw(p.prepare(frames)), p.targets(states)))

    assert trained.global_step == 30 and trained.best is not None
    assert loss(module) < 0.6 * loss(fresh), (loss(fresh), loss(module))
    events = list((trained.run_dir / "tensorboard").glob("events.out.tfevents.*"))
    assert events and json.loads((trained.run_dir / "run.json").read_text())["kind"] == "reward"
    logged = trained.module.trainer.callback_metrics
    for name in ("val/loss", "val/registration_abs_err_px", "val/vertex_px", "val/position_px", "val/angle_deg"):
        assert math.isfinite(float(logged[name])), name


def test_checkpoint_round_trip_is_exact(trained, store, tmp_path):
    loaded = RewardPredictorModule.load_from_checkpoint(trained.last)
    frames, _ = _frames(store, 1)
    trained.module.eval()
    with torch.no_grad():
        assert torch.equal(loaded.predictor(frames), trained.module.predictor(frames))
    assert loaded.config == trained.module.config and loaded.input_size == 32
    assert set(loaded.predictor.normalizer.keys()) >= {"img", "state"}
    meta = torch.load(trained.last, weights_only=True)["gpc"]
    assert (meta["kind"], meta["task"], meta["obs"], meta["input_size"]) == ("reward", "pusht", "image", 32)
    ckpt = torch.load(trained.last, weights_only=True)
    ckpt["gpc"]["kind"] = "policy"
    torch.save(ckpt, tmp_path / "policy.ckpt")
    with pytest.raises(DataError, match="is a 'policy' checkpoint, expected a 'reward' checkpoint"):
        RewardPredictorModule.load_from_checkpoint(tmp_path / "policy.ckpt")


def test_image_reward_shapes_goals_aggregation_and_gradients(trained, store):
    reward = ImageReward.from_checkpoint(trained.last)
    assert isinstance(reward, Reward) and reward.input_size == 32
    assert not any(p.requires_grad for p in reward.parameters())
    frames, _ = _frames(store)
    for size in (48, 96):  # a world model's smaller frames, and the recorded size
        futures = torch.nn.functional.interpolate(frames[:6], size=(size, size), mode="area").reshape(3, 2, 3, size, size)
        futures.requires_grad_(True)
        score = reward(futures)
        assert score.shape == (3,) and torch.isfinite(score).all() and (score <= 0).all()
        score.sum().backward()
        assert torch.isfinite(futures.grad).all() and float(futures.grad.abs().sum()) > 0
    futures = futures.detach()
    per_step = reward.per_step(futures)
    assert per_step.shape == (3, 2) and torch.allclose(score, per_step[:, -1])
    disc = ImageReward.from_checkpoint(trained.last, config=RewardConfig("discounted", 0.5))(futures)
    assert torch.allclose(disc, per_step[:, 0] + 0.5 * per_step[:, 1])
    poses = reward.poses(futures)  # (K, T, 3): a goal at each candidate's own final predicted pose scores 0
    assert poses.shape == (3, 2, 3)
    assert torch.allclose(reward(futures, goal=poses[:, -1]), torch.zeros(3), atol=1e-3)
    # the same numbers as the state reward on the predicted poses (one reward interface)
    states = torch.cat([torch.zeros(3, 2, 2), poses], dim=-1)
    assert torch.allclose(RegistrationReward(geometry.TEE_BOXES, GOAL, LAYOUT.pose_dims)(states), score.detach(), atol=1e-4)
    other = ImageReward(trained.module.predictor, goal=[100.0, 100.0, 0.0])
    assert not torch.allclose(other(futures), score.detach())
    with pytest.raises(ValueError, match=r"expected \(K, T, 3, S, S\)"):
        reward(futures[0])


def test_shift_augmentation_moves_the_label_with_the_picture():
    state = np.array([200.0, 150.0, 260.0, 240.0, 0.7])
    frame = torch.from_numpy(draw_state(state)).permute(2, 0, 1)[None].float() / 255.0
    torch.manual_seed(3)
    shifted, shift = random_shift(frame, 3.0)
    d = shift[0].numpy().astype(np.float64) * geometry.WORKSPACE / 96  # world units

    def error(sign: float) -> float:  # the scene redrawn with everything moved by sign * d, away from the walls
        moved = draw_scene(state[:2] + sign * d, np.array([*(state[2:4] + sign * d), state[4]]),
                           geometry.GOAL_POSE + [*(sign * d), 0.0])
        moved_t = torch.from_numpy(moved).permute(2, 0, 1)[None].float() / 255.0
        return float((shifted - moved_t)[..., 10:-10, 10:-10].abs().mean())

    assert float(shift.abs().min()) > 0.5  # a visible shift in both directions
    assert error(1.0) < 0.4 * error(0.0) and error(1.0) < 0.3 * error(-1.0), (error(1.0), error(0.0), error(-1.0))
    assert torch.allclose(random_blur(frame, 0.0, 1.0), frame, atol=1e-5)
    blurred = random_blur(frame.expand(4, -1, -1, -1), 1.0, 1.5)
    assert blurred.shape == (4, 3, 96, 96) and abs(float(blurred.mean() - frame.mean())) < 5e-3


def test_config_validation_and_task_fields():
    with pytest.raises(ValueError, match="pool 'max'"):
        RewardPredictorConfig(task="pusht", pool="max")
    with pytest.raises(ValueError, match="task must be named"):
        RewardPredictorConfig()
    with pytest.raises(ValueError, match="with_task"):
        RewardPredictorConfig(task="pusht").check_task()
    with pytest.raises(ValueError, match="profile 'huge'"):
        reward_profile("huge", LAYOUT)
    config = tiny()
    assert RewardPredictorConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    assert reward_profile("paper", LAYOUT).config.mlp_dims == (512, 256, 128) and reward_profile("paper", LAYOUT).config.resnet_width == 64


def test_evaluation_against_the_true_registration_loss(trained, store):
    report = evaluate_reward_predictor(trained.module, [store], split="val")
    assert report["episodes"] == 2 and report["frames"] == 24
    assert report["frame_size"] == 96 and report["input_size"] == 32
    for key in ("registration_mae_px", "constant_baseline_mae_px", "vertex_px", "position_px", "angle_deg", "spearman"):
        assert math.isfinite(report[key]), key
    assert sum(b["frames"] for b in report["by_true_registration"]) == 24
    small = evaluate_reward_predictor(trained.module, [store], split="all", episodes=1, stride=3, frame_size=48)
    assert (small["episodes"], small["frames"], small["frame_size"]) == (1, 4, 48)


def test_cli_trains_and_evaluates(store, tmp_path):
    cli = CliRunner()
    out = tmp_path / "reward-tiny"
    common = ["--dataset", str(store), "--profile", "tiny", "--max-steps", "3", "--batch-size", "8",
              "--accelerator", "cpu", "--no-progress", "--image-size", "24"]
    ok = cli.invoke(reward_app, ["train", "--out", str(out), *common])
    assert ok.exit_code == 0, ok.output
    assert "step 3; last:" in ok.output
    again = cli.invoke(reward_app, ["train", "--out", str(out), *common])
    assert isinstance(again.exception, DataError) and "--resume" in str(again.exception)
    last = out / "checkpoints" / "last.ckpt"
    assert RewardPredictorModule.load_from_checkpoint(last).input_size == 24
    ood = make_store(tmp_path / "ood.zarr", episodes=2, length=5, seed=7)
    ev = cli.invoke(reward_app, ["eval", str(last), "--dataset", str(store), "--ood", str(ood), "--stride", "2"])
    assert ev.exit_code == 0, ev.output
    reports = json.loads((out / "eval" / "reward_eval.json").read_text())
    assert [r["split"] for r in reports] == ["val", "all"] and reports[1]["frames"] == 6
    assert all(r["checkpoint"] == str(last) for r in reports)
    assert "ood.zarr" in ev.output and (out / "eval" / "reward_eval.md").is_file()


def test_evaluation_reads_the_human_data(trained, human_data):
    """Diffusion Policy's store keeps frames as float32 0..255; they are read as the uint8 frames of ours."""
    report = evaluate_reward_predictor(trained.module, [human_data], split="all", episodes=1, stride=20)
    assert report["episodes"] == 1 and report["frames"] >= 3 and math.isfinite(report["registration_mae_px"])


def _two_object_layout():
    """A square whose goal ignores its turn, and a disc: the swap task's shape, a goal per episode."""
    from gpc.datasets.layout import ActionBox, FrameLayout, ObjectLayout, StateLayout, TaskLayout

    square = ((-30.0, -30.0), (30.0, -30.0), (30.0, 30.0), (-30.0, 30.0))
    return TaskLayout(name="two", state=StateLayout(dim=7, agent_xy=(0, 1), angle_dims=(4,), action_targets=(0, 1)),
                      action=ActionBox(dim=2, low=0.0, high=512.0),
                      objects=(ObjectLayout("cube", pose=(2, 3, 4), angle=4, vertices=square),
                               ObjectLayout("sphere", pose=(5, 6), vertices=((0.0, 0.0),))),
                      frame=FrameLayout(extent=(0.0, 512.0), marker_size=15.0))


def test_a_predictor_of_several_objects_reads_each_pose_and_scores_against_per_episode_goals():
    from gpc.datasets.normalizer import MinMaxNormalizer
    from gpc.models.rewards.learned import PosePredictor
    from gpc.models.rewards.registration import pose_errors

    layout = _two_object_layout()
    config = reward_profile("tiny", layout).config
    assert config.sizes == (3, 2) and config.pose_dims == (2, 3, 4, 5, 6) and config.goal is None
    assert [len(v) for v in config.object_vertices] == [4, 1]
    rng = np.random.default_rng(0)
    states = torch.tensor(np.c_[rng.uniform(0, 512, (8, 4)), rng.uniform(-3, 3, 8), rng.uniform(0, 512, (8, 2))], dtype=torch.float32)
    normalizer = MinMaxNormalizer.fit({"img": np.zeros((2, 3)), "state": states.numpy()}, image_keys=("img",))
    predictor = PosePredictor(config, normalizer)
    labels = predictor.targets(states)
    assert labels.shape == (8, 6)  # cube x, y, cos, sin; sphere x, y
    back = predictor.to_pose(labels)  # labels read back are the states' poses (angles wrapped)
    torch.testing.assert_close(back[:, [0, 1, 3, 4]], states[:, [2, 3, 5, 6]], atol=1e-3, rtol=0)
    torch.testing.assert_close(torch.cos(back[:, 2]), torch.cos(states[:, 4]), atol=1e-5, rtol=0)
    errors = pose_errors(back, states[:, [2, 3, 4, 5, 6]], [torch.tensor(v) for v in config.object_vertices], None, config.sizes)
    assert errors["vertex_px"].abs().max() < 1e-2 and "registration_true_px" not in errors
    reward = ImageReward(predictor.requires_grad_(False))
    frames = torch.rand(3, 2, 3, 32, 32, requires_grad=True)
    with pytest.raises(ValueError, match="pass the episode's goal"):
        reward(frames)
    scores = reward(frames, torch.tensor([[100.0, 100.0, 0.0, 300.0, 300.0]] * 3))
    assert scores.shape == (3,) and bool((scores < 0).all())
    scores.sum().backward()
    assert frames.grad is not None and frames.grad.abs().sum() > 0
