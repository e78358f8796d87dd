"""DART demonstrations (`gpc collect --dart`): the expert runs with correlated noise, the store keeps what ran as
``action`` (the world model's) and what the expert asked for as ``expert_action`` (the policy's, `--labels`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from faults import inline, one_line
from toy_task import REACH

from gpc.datasets.datamodule import DataConfig, EpisodeDataModule
from gpc.datasets.store import EpisodeStore
from gpc.harness.collection import CollectJob, collect
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.trainer import train
from gpc.tasks import get_task, register_task
from gpc.tasks.base import ActionNoise
from gpc.tasks.swap.env import SwapEnv

SWAP = get_task("swap")
NOISE = ActionNoise(0.01, 2.0)


def _replay(actions: np.ndarray, seed: int) -> np.ndarray:
    """The states the swap scene passes through when ``actions`` run from the reset of ``seed``."""
    env = SwapEnv(obs_type="state")
    env.reset(seed=seed)
    states = [env.sim.state()]
    for action in actions[:-1]:
        env.step(action)
        states.append(env.sim.state())
    return np.array(states)


def test_noisy_demonstrations_keep_what_ran_and_what_the_expert_asked_for():
    clean, clean_stats = SWAP.record("expert", 3, "fixed", False, 400, None)
    data, stats = SWAP.record("expert", 3, "fixed", False, 400, NOISE)
    assert "expert_action" not in clean and "expert_action" in data
    assert clean_stats.success and stats.success and stats.steps != clean_stats.steps  # noise moved the episode
    again, _ = SWAP.record("expert", 3, "fixed", False, 400, NOISE)
    assert all(np.array_equal(data[k], again[k]) for k in data)  # the seed draws the noise
    diff = (data["action"] - data["expert_action"]).astype(np.float64)
    sigma = NOISE.scale * 512.0
    assert 0.6 * sigma < diff.std() < 1.4 * sigma, diff.std()
    lag = np.mean([np.corrcoef(diff[:-1, i], diff[1:, i])[0, 1] for i in range(2)])
    assert abs(lag - np.exp(-1 / NOISE.steps)) < 0.15, lag  # correlated over about `steps` steps, as said
    # `action` is what ran: replaying it from the reset gives the stored states; the labels do not.
    ran = _replay(data["action"], 3)
    assert np.abs(ran - data["state"]).max() < 0.05
    assert np.abs(_replay(data["expert_action"], 3) - data["state"]).max() > 5.0


def test_the_noise_is_checked_and_each_task_clips_to_its_action_box():
    for bad in (0.0, 0.6):
        with pytest.raises(ValueError, match="--dart"):
            ActionNoise(bad)
    with pytest.raises(ValueError, match="--dart-steps"):
        ActionNoise(0.01, 0.5)
    stack = get_task("stack")
    data, _ = stack.record("expert", 1, "fixed", False, 60, ActionNoise(0.05))
    from gpc.tasks.stack.scene import ACTION_HIGH as high
    from gpc.tasks.stack.scene import ACTION_LOW as low

    assert (data["action"] >= low - 1e-6).all() and (data["action"] <= high + 1e-6).all()
    assert not np.allclose(data["action"], data["expert_action"])


def test_collect_names_the_noise_resumes_only_the_same_and_refuses_it_elsewhere(tmp_path):
    out = tmp_path / "dart.zarr"
    args = ["collect", "--task", "swap", "--out", str(out), "--episodes", "2", "--seed", "5", "--no-images",
            "--dart", "0.01", "--dart-steps", "2"]
    rc, text = inline(*args)
    assert rc == 0, text
    store = EpisodeStore.open(out)
    assert store.attrs["collector"]["dart"] == {"scale": 0.01, "steps": 2.0}
    assert "expert_action" in store.keys and store.attrs["keys"] == sorted(store.keys)
    before = store.read("action").copy()
    one_line(inline(*args[:-3], "0.02", "--dart-steps", "2"), 2, str(out), "dart")
    one_line(inline(*args[:-4]), 2, str(out), "collector")  # a clean expert is other data
    assert np.array_equal(EpisodeStore.open(out).read("action"), before)
    one_line(inline("collect", "--task", "swap", "--out", str(tmp_path / "x"), "--explore", "--dart", "0.01"), 2, "--dart")
    one_line(inline("collect", "--task", "swap", "--out", str(tmp_path / "y"), "--dart", "0.9"), 2, "--dart 0.9")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_a_task_written_before_dart_collects_as_it_did_and_refuses_noise(tmp_path):
    """A user's task whose ``record`` takes the five arguments it took before is called with five."""
    register_task(REACH)
    summary = collect(CollectJob(task="reach", out=tmp_path / "reach.zarr", episodes=2, images=False, max_steps=20))
    assert summary.written == 2
    with pytest.raises(ValueError, match="task reach's record takes no action noise"):
        CollectJob(task="reach", out=tmp_path / "noisy.zarr", episodes=2, images=False, noise=NOISE)


def test_a_policy_learns_the_labels_and_other_stores_give_their_actions(tmp_path):
    dart = tmp_path / "dart.zarr"
    clean = tmp_path / "clean.zarr"
    for out, extra in ((dart, ["--dart", "0.01", "--dart-steps", "2"]), (clean, [])):
        rc, text = inline("collect", "--task", "swap", "--out", str(out), "--episodes", "2", "--no-images", *extra)
        assert rc == 0, text
    config = DataConfig(paths=(str(dart), str(clean)), action_source="expert_action")
    arrays = EpisodeDataModule(config).arrays
    want = np.concatenate([EpisodeStore.open(dart).read("expert_action"), EpisodeStore.open(clean).read("action")])
    assert np.array_equal(arrays.data["action"], want)
    assert not np.array_equal(EpisodeDataModule(DataConfig(paths=(str(dart), str(clean)))).arrays.data["action"], want)
    policy = dataclasses.replace(policy_profile("tiny", "state", SWAP.layout).config, labels="expert_action")
    run = train(PolicyModule, policy, [dart], _run(tmp_path, "labels"))
    loaded = PolicyModule.load_from_checkpoint(run.last)
    assert loaded.config.labels == "expert_action"
    # its action normaliser spans the expert's labels on its training episodes, not the noisier actions executed

    def span(labels: str) -> torch.Tensor:
        data = PolicyModule.data_config(dataclasses.replace(policy, labels=labels), (str(dart),), _run(tmp_path, "x"), (0, 0.05))
        return EpisodeDataModule(data).normalizer.scales["action"]

    assert torch.equal(loaded.normalizer.scales["action"], span("expert_action"))
    assert not torch.equal(loaded.normalizer.scales["action"], span("action"))
    assert json.loads((tmp_path / "labels" / "run.json").read_text())["config"]["labels"] == "expert_action"
    with pytest.raises(ValueError, match="--labels 'noisy'"):
        dataclasses.replace(policy, labels="noisy")


def _run(tmp: Path, name: str):
    from gpc.models.training.config import RunConfig

    return RunConfig(run_dir=tmp / name, max_steps=2, batch_size=16, progress=False, accelerator="cpu")
