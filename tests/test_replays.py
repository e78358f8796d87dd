"""`gpc eval ranking --save-replays`: every decision's proposals replayed in the simulator, kept as short episodes laid
out as a world model's windows, and a world model trains on them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.sequence import window_starts
from gpc.datasets.store import EpisodeStore
from gpc.datasets.windows import load_stores
from gpc.harness.ownership import digest_file
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.eval_state import held_out_windows
from gpc.models.world_models.module import WorldModelModule

pytestmark = pytest.mark.usefixtures("one_thread")
K, STEPS, N_ACTION = 3, 24, 8  # 3 decisions per episode, the first without an executed action before it


@pytest.fixture(scope="module")
def replays(ckpts, tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("replays")
    args = ["eval", "ranking", ckpts["policy"], "-K", str(K), "--seeds", "70000:70002", "--max-steps", str(STEPS),
            "--batch", "2", "--scorer", f"rank={ckpts['wm']}"]
    res = CliRunner().invoke(app, args + ["--save-replays", str(tmp / "replays.zarr"), "--out", str(tmp / "probe.md")])
    assert res.exit_code == 0, res.output
    saved = json.loads((tmp / "probe.json").read_text())
    assert saved["replays"]["episodes"] == 2 * 2 * K
    res = CliRunner().invoke(app, args + ["--out", str(tmp / "plain.md")])  # the longer history kept changes no figure
    assert res.exit_code == 0 and json.loads((tmp / "plain.json").read_text())["scorers"] == saved["scorers"]
    return tmp / "replays.zarr"


def test_each_replay_starts_from_the_observed_history_and_chains_into_the_next_decision(ckpts, replays):
    store = EpisodeStore.open(replays)
    assert list(store.episode_seeds()) == [70000] * 2 * K + [70001] * 2 * K  # per seed, decision after decision
    assert store.attrs["collector"]["kind"] == "replays" and store.attrs["collector"]["k"] == K
    assert store.attrs["collector"]["checkpoints"] == {ckpts["policy"]: digest_file(Path(ckpts["policy"]))}
    assert store.attrs["episode_starts"] == "mid-motion" and store.attrs["collector"]["history"] == 3
    episodes = [store.episode(i) for i in range(store.n_episodes)]
    policy = PolicyModule.load_from_checkpoint(ckpts["policy"]).config
    assert (policy.n_obs_steps, policy.horizon) == (2, 16)
    assert all(len(e["state"]) == len(e["action"]) == 3 + 15 for e in episodes)  # 3 observed states, 15 replayed
    for seed in range(2):
        first, second = episodes[seed * 2 * K : seed * 2 * K + K], episodes[seed * 2 * K + K : (seed + 1) * 2 * K]
        for group in (first, second):  # the K proposals of one decision: one history, the actions before, K futures
            assert all(np.array_equal(e["state"][:3], group[0]["state"][:3]) for e in group)
            assert all(np.array_equal(e["action"][:2], group[0]["action"][:2]) for e in group)
            assert not np.allclose(group[0]["state"][3:], group[1]["state"][3:])
        # the probe executes the first proposal's N_ACTION actions: its replay is where the episode went, exactly
        executed = first[0]  # state 2 + j follows action 2 + j - 1 (proposal action j)
        np.testing.assert_allclose(second[0]["state"][:3], executed["state"][N_ACTION : N_ACTION + 3], atol=1e-2)
        np.testing.assert_array_equal(second[0]["action"][:2], executed["action"][N_ACTION : N_ACTION + 2])


def test_a_world_model_trains_on_the_replays_beside_its_data(ckpts, replays, tmp_path):
    wm = WorldModelModule.load_from_checkpoint(ckpts["wm"])
    arrays = load_stores([Path(ckpts["dir"]) / "expert.zarr", replays], ["state", "action"])
    assert arrays.mid_motion is not None and arrays.mid_motion.sum() == 2 * 2 * K and not arrays.mid_motion[:4].any()
    spec = WorldModelModule.data_config(wm.config, (), RunConfig(run_dir=tmp_path, max_steps=1), (0, 0.0)).spec
    assert spec.pad_before == 1 and spec.horizon <= 18  # (this tiny model's horizon is shorter than the policy's)
    rows = window_starts(arrays.episode_ends, np.arange(4, arrays.n_episodes), spec, mid_motion=arrays.mid_motion)
    assert len(rows) == 2 * 2 * K * (18 - spec.horizon + 1) and rows[:, 2].min() == 0  # never padded at the start
    assert len(window_starts(arrays.episode_ends, np.arange(4), spec, mid_motion=arrays.mid_motion)) > 4
    _, _, idx, _ = held_out_windows(wm, [replays], ["state", "action"], split="all")  # `gpc eval world-model`'s windows
    assert len(idx) == 2 * 2 * K * (18 - spec.horizon + 1) and np.all(np.diff(idx, axis=1) == 1)  # none padded
    config = dataclasses.replace(wm.config, phase=2)
    run = train(WorldModelModule, config, [Path(ckpts["dir"]) / "expert.zarr", replays],
                RunConfig(run_dir=tmp_path / "wm", max_steps=3, batch_size=16, progress=False, accelerator="cpu"),
                init=ckpts["wm"])
    assert run.last.exists()


@pytest.mark.parametrize("case", ["exists", "nothing", "too short"])
def test_refusals_name_the_option_and_write_nothing(ckpts, tmp_path, case):
    target = tmp_path / "replays.zarr"
    if case == "exists":
        target.mkdir()
        (target / "mine.txt").write_text("keep")
    args = ["eval", "ranking", ckpts["policy"], "--seeds", "70000:70001", "--max-steps", "8", "--out", str(tmp_path / "p.md")]
    res = CliRunner().invoke(app, args + (["--save-replays", str(target)] if case != "nothing" else []))
    assert res.exit_code == 2
    expect = {"exists": "already exists; --save-replays writes a new store", "nothing": "--save-replays STORE",
              "too short": "the first at step 8; raise it above 8"}[case]  # 8 steps: one decision, none executed before it
    assert expect in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not (tmp_path / "p.md").exists() and not (tmp_path / "p.json").exists()
    assert case != "exists" or (target / "mine.txt").read_text() == "keep"
