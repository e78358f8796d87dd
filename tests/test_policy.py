"""Diffusion Policy end to end on CPU: real Zarr stores, real Lightning training, numbers asserted."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gpc.cli.train import train_app
from gpc.datasets.datamodule import EpisodeDataModule
from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore
from gpc.models.planning.protocols import ActionProposer
from gpc.models.policy.config import policy_profile
from gpc.models.policy.denoiser import ActionDenoiser
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import TrainingDiverged, train
from gpc.tasks.pusht import LAYOUT

ROOT = Path(__file__).resolve().parents[1]


def make_store(path: Path, episodes: int = 6, length: int = 40, image: int = 16, keypoints: bool = True) -> Path:
    """Smooth agent paths (actions lead the agent) with keypoints and small random images."""
    rng = np.random.default_rng(0)
    store = EpisodeStore.create(path, {"task": "pusht"})
    for e in range(episodes):
        t = np.linspace(0, 1, length)[:, None]
        start = rng.uniform(50, 250, 2)
        agent = start + 200 * np.hstack([t, t ** 2]) + rng.normal(0, 1, (length, 2))
        state = np.hstack([agent, np.full((length, 2), 256.0), np.full((length, 1), 0.7)]).astype(np.float32)
        data = {"state": state, "action": (agent + 5).astype(np.float32),
                "img": rng.uniform(0, 255, (length, image, image, 3)).astype(np.float32)}
        if keypoints:
            data["keypoint"] = (agent[:, None, :] + rng.normal(0, 5, (length, 9, 2))).astype(np.float32)
        store.append_episode(data, seed=e)
    return path


def tiny(obs: str = "state", **optim):
    policy = policy_profile("tiny", obs, LAYOUT).config
    if obs == "image":
        policy = dataclasses.replace(policy, encoder=dataclasses.replace(policy.encoder, crop_size=12))
    if optim:
        policy = dataclasses.replace(policy, optim=dataclasses.replace(policy.optim, **optim))
    return policy


def run(tmp: Path, name: str, **kw) -> RunConfig:
    kw = {"max_steps": 4, "batch_size": 16, "progress": False, "accelerator": "cpu", **kw}
    return RunConfig(run_dir=tmp / name, **kw)


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return make_store(tmp_path_factory.mktemp("data") / "demo.zarr")


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    """A state policy trained 50 steps on the tiny store (lr 3e-3, warm-up 5)."""
    return train(PolicyModule, tiny(), [store], run(tmp_path_factory.mktemp("runs"), "state", max_steps=50, checkpoint_every=20))


def _history(store: Path, episode: int = 0, step: int = 5) -> dict[str, np.ndarray]:
    ep = EpisodeStore.open(store).episode(episode)
    return {k: ep[k][step - 1 : step + 1] for k in ("state", "keypoint", "img")}


def test_loss_decreases_over_fifty_steps(trained, store):
    windows = PolicyModule.data_config(trained.module.config, (str(store),), run(Path("/unused"), "x", batch_size=64), (0, 0.05))
    data = EpisodeDataModule(windows)
    batch = next(iter(data.train_dataloader()))
    fresh = PolicyModule(trained.module.config, normalizer=data.normalizer)

    def fixed_loss(module: PolicyModule) -> float:  # same windows, same noise, same steps
        obs, action = module._split_batch(batch)
        with torch.no_grad():
            return float(module.model.loss(obs, action, generator=torch.Generator().manual_seed(0))[0])

    before, after = fixed_loss(fresh), fixed_loss(trained.module)
    assert trained.global_step == 50
    # A network predicting zero noise scores 1.0; the fresh one scores about 1.2.
    assert after < 0.65 * before and after < 0.75, (before, after)
    assert trained.best is not None and trained.best.name == "best.ckpt" and trained.best_val_loss < 1.0


def test_samples_have_shape_are_seeded_and_stay_in_range(trained, store):
    policy, obs = trained.module, _history(store)
    a = policy.sample(obs, num_samples=8, generator=torch.Generator().manual_seed(0))
    b = policy.sample(obs, num_samples=8, generator=torch.Generator().manual_seed(0))
    c = policy.sample(obs, num_samples=8, generator=torch.Generator().manual_seed(1))
    assert a.shape == (8, 16, 2) and torch.equal(a, b) and not torch.allclose(a, c)
    lo, hi = policy.normalizer.unnormalize("action", torch.tensor([-1.0, 1.0])[:, None]).unbind(0)
    for method, steps in (("ddim", 10), ("ddpm", 100)):
        x = policy.sample(obs, num_samples=16, generator=torch.Generator().manual_seed(2), method=method, steps=steps)
        assert torch.isfinite(x).all()
        assert (x >= lo - 1e-3).all() and (x <= hi + 1e-3).all(), method
    assert policy.action_slice == slice(1, 9)
    assert isinstance(policy, ActionProposer)


@pytest.mark.parametrize("method,steps", [("ddim", 4), ("ddpm", 20)])
def test_batched_sampling_equals_per_history_sampling(trained, store, method, steps):
    policy = trained.module
    histories = [_history(store, e, s) for e, s in ((0, 3), (1, 10), (2, 30))]
    batched = {k: np.stack([h[k] for h in histories]) for k in histories[0]}
    gens = [torch.Generator().manual_seed(10 + i) for i in range(3)]
    together = policy.sample_batch(batched, num_samples=5, generator=gens, method=method, steps=steps)
    assert together.shape == (3, 5, 16, 2)
    for i, h in enumerate(histories):
        alone = policy.sample(h, num_samples=5, generator=torch.Generator().manual_seed(10 + i), method=method, steps=steps)
        assert torch.allclose(together[i], alone, atol=1e-3), (i, (together[i] - alone).abs().max())
    with pytest.raises(ValueError, match="2 generators for 3"):
        policy.sample_batch(batched, 5, generator=gens[:2])
    with pytest.raises(ValueError, match="lacks key 'state'"):
        policy.sample({"keypoint": histories[0]["keypoint"]})


def test_checkpoint_round_trip_gives_identical_samples(trained, store):
    loaded = PolicyModule.load_from_checkpoint(trained.last, task="pusht", obs_type="state")
    assert not loaded.training and loaded.config == trained.module.config
    assert int(loaded.ema.updates) == 50 and loaded.normalizer.keys() == trained.module.normalizer.keys()
    obs = _history(store)
    for method in ("ddim", "ddpm"):
        a = trained.module.sample(obs, 6, torch.Generator().manual_seed(3), method=method, steps=10)
        b = loaded.sample(obs, 6, torch.Generator().manual_seed(3), method=method, steps=10)
        assert torch.equal(a, b)
    best = PolicyModule.load_from_checkpoint(trained.best)
    assert torch.isfinite(best.sample(obs, 2)).all()


def test_wrong_kind_task_obs_and_corrupt_checkpoints(trained, tmp_path):
    ckpt = torch.load(trained.last, weights_only=True)
    assert ckpt["gpc"] == {"format": 1, "kind": "policy", "task": "pusht", "obs": "state"}
    with pytest.raises(DataError, match="task 'pusht', expected task 'cartpole'"):
        PolicyModule.load_from_checkpoint(trained.last, task="cartpole")
    with pytest.raises(DataError, match="obs 'state', expected 'image'"):
        PolicyModule.load_from_checkpoint(trained.last, obs_type="image")
    ckpt["gpc"]["kind"] = "world_model"
    torch.save(ckpt, tmp_path / "wm.ckpt")
    with pytest.raises(DataError, match="is a 'world_model' checkpoint, expected a 'policy'"):
        PolicyModule.load_from_checkpoint(tmp_path / "wm.ckpt")
    torch.save({"state_dict": {}}, tmp_path / "foreign.ckpt")
    with pytest.raises(DataError, match="not a gpc checkpoint"):
        PolicyModule.load_from_checkpoint(tmp_path / "foreign.ckpt")
    (tmp_path / "cut.ckpt").write_bytes(trained.last.read_bytes()[:5000])
    with pytest.raises(DataError, match="corrupt checkpoint"):
        PolicyModule.load_from_checkpoint(tmp_path / "cut.ckpt")
    with pytest.raises(DataError, match="no such checkpoint"):
        PolicyModule.load_from_checkpoint(tmp_path / "missing.ckpt")


def test_resume_continues_the_step_count(store, tmp_path):
    first = train(PolicyModule, tiny(), [store], run(tmp_path, "r", max_steps=6))
    assert first.global_step == 6
    with pytest.raises(DataError, match="already holds a training run"):
        train(PolicyModule, tiny(), [store], run(tmp_path, "r", max_steps=12))
    second = train(PolicyModule, tiny(), [store], run(tmp_path, "r", max_steps=12, resume=True))
    assert second.global_step == 12
    ckpt = torch.load(second.last, weights_only=True)
    assert ckpt["global_step"] == 12 and int(ckpt["state_dict"]["ema.updates"]) == 12
    with pytest.raises(DataError, match="nothing to resume"):
        train(PolicyModule, tiny(), [store], run(tmp_path, "fresh", resume=True))
    with pytest.raises(DataError, match="obs 'state', not 'keypoints'"):
        train(PolicyModule, tiny("keypoints"), [store], run(tmp_path, "r", max_steps=14, resume=True))


def test_non_finite_loss_stops_and_keeps_the_last_good_weights(store, tmp_path, monkeypatch):
    real_loss, calls = ActionDenoiser.loss, {"n": 0}

    def loss_going_nan(self, obs, action, generator=None):
        loss, logs = real_loss(self, obs, action, generator)
        if self.training:
            calls["n"] += 1
            if calls["n"] > 3:
                loss = loss * float("nan")
        return loss, logs

    monkeypatch.setattr(ActionDenoiser, "loss", loss_going_nan)
    with pytest.raises(TrainingDiverged, match="non-finite at step 3"):
        train(PolicyModule, tiny(), [store], run(tmp_path, "nan", max_steps=20))
    monkeypatch.undo()
    ckpt = torch.load(tmp_path / "nan" / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["global_step"] <= 4 and int(ckpt["state_dict"]["ema.updates"]) == 3
    assert all(torch.isfinite(v).all() for v in ckpt["state_dict"].values() if v.is_floating_point())


@pytest.mark.parametrize("obs", ["keypoints", "image"])
def test_keypoint_and_image_policies_train_and_sample(store, tmp_path, obs):
    result = train(PolicyModule, tiny(obs), [store], run(tmp_path, obs, max_steps=3))
    policy = PolicyModule.load_from_checkpoint(result.last, obs_type=obs)
    shapes = dict(policy.config.encoder.obs_shapes)
    assert shapes["state"] == (5,) and (shapes.get("keypoint") == (9, 2) or shapes.get("img") == (16, 16, 3))
    x = policy.sample(_history(store), num_samples=3, generator=torch.Generator().manual_seed(0))
    assert x.shape == (3, 16, 2) and torch.isfinite(x).all()


def test_dataset_without_the_obs_key_is_a_clear_error(tmp_path):
    path = make_store(tmp_path / "nokp.zarr", episodes=2, keypoints=False)
    with pytest.raises(DataError, match=r"nokp.zarr: missing key data/keypoint"):
        train(PolicyModule, tiny("keypoints"), [path], run(tmp_path, "kp"))


def test_cli_trains_and_reports_errors(store, tmp_path):
    cli = CliRunner()
    args = ["policy", "--dataset", str(store), "--out", str(tmp_path / "cli"), "--profile", "tiny", "--max-steps", "3",
            "--batch-size", "16", "--accelerator", "cpu", "--no-progress"]
    ok = cli.invoke(train_app, args)
    assert ok.exit_code == 0, ok.output
    assert "step 3; last:" in ok.output and (tmp_path / "cli" / "checkpoints" / "last.ckpt").is_file()
    assert (tmp_path / "cli" / "run.json").is_file() and any((tmp_path / "cli" / "tensorboard").iterdir())
    again = cli.invoke(train_app, args)
    assert isinstance(again.exception, DataError) and "--resume" in str(again.exception)
    bad = cli.invoke(train_app, args[:-1] + ["--task", "chess"])
    assert bad.exit_code != 0 and "unknown task 'chess'" in bad.output
    assert "--obs" in cli.invoke(train_app, ["policy", "--help"]).output
    lr = cli.invoke(train_app, ["policy", "--dataset", str(store), "--out", str(tmp_path / "lr"), "--profile", "tiny",
                                "--max-steps", "1", "--batch-size", "8", "--accelerator", "cpu", "--no-progress",
                                "--lr", "0.0005"])
    assert lr.exit_code == 0, lr.output
    assert PolicyModule.load_from_checkpoint(tmp_path / "lr" / "checkpoints" / "last.ckpt").config.optim.lr == 0.0005


def test_policy_trains_on_the_human_data(human_data, tmp_path):
    result = train(PolicyModule, tiny("keypoints"), [human_data], run(tmp_path, "human", max_steps=2, batch_size=32))
    assert result.global_step == 2
    assert dict(result.module.config.encoder.obs_shapes) == {"keypoint": (9, 2), "state": (5,)}
    assert result.best is None or result.best.is_file()


def test_two_process_ddp_on_cpu(store, tmp_path):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "gpc.cli.train", "policy", "--dataset", str(store), "--out", str(out),
           "--profile", "tiny", "--max-steps", "3", "--batch-size", "8", "--accelerator", "cpu", "--devices", "2",
           "--strategy", "ddp", "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["global_step"] == 3 and ckpt["gpc"]["kind"] == "policy"
    assert "MEMBER: 2/2" in done.stdout + done.stderr and done.stdout.count("step 3; last:") == 1
