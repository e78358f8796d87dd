"""`gpc record`: a planner's closed-loop episodes as a store, real simulator and real Zarr on disk."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks import get_task
from gpc.tasks.pusht import LAYOUT
from gpc.tasks.pusht.env import PushTEnv

pytestmark = pytest.mark.usefixtures("one_thread")
runner = CliRunner()


def _opt(models: dict, *extra: str) -> list[str]:
    return [str(models["policy"]), "--planner", "opt", "-M", "2", "--world-model", str(models["wm"]),
            "--max-steps", "12", "--batch", "2", *extra]


def test_record_stores_the_episodes_eval_scores(tiny_pusht, tmp_path):
    store_path = tmp_path / "opt.zarr"
    res = runner.invoke(app, ["record", *_opt(tiny_pusht, "--out", str(store_path), "--episodes", "2", "--seed", "60000")])
    assert res.exit_code == 0, res.output
    store = EpisodeStore.open(store_path)
    assert store.n_episodes == 2 and list(store.episode_seeds()) == [60000, 60001]
    assert sorted(store.keys) == get_task("pusht").record_keys(True, "fixed")  # frames too, though the policy reads keypoints
    assert store.shape("img")[1:] == (96, 96, 3) and store.read("img").dtype == np.uint8
    assert store.attrs["collector"]["kind"] == "closed-loop" and store.attrs["collector"]["controller"] == "opt M=2"

    # the very episodes `gpc eval` scores for these seeds
    res = runner.invoke(app, ["eval", *_opt(tiny_pusht, "--seeds", "60000:60002", "--out", str(tmp_path / "eval"))])
    assert res.exit_code == 0, res.output
    scored = json.loads((tmp_path / "eval" / "episodes.json").read_text())
    assert [r["score"] for r in scored] == pytest.approx(list(store.episode_scores()))
    assert [r["steps"] for r in scored] == list(np.diff(np.concatenate([[0], store.episode_ends])))

    # faithful to the simulator: each step holds the state before its action, and the contacts that led to it
    for i, seed in enumerate((60000, 60001)):
        ep, env = store.episode(i), PushTEnv()
        env.reset(seed=seed)
        contacts = 0
        for state, action, n in zip(ep["state"], ep["action"], ep["n_contacts"]):
            np.testing.assert_allclose(state, env.sim.state(), atol=1e-3)
            assert n[0] == contacts
            contacts = env.step(action.astype(np.float64))[4]["n_contacts"]

    # resuming runs only the missing seed and leaves the recorded ones as they were
    before = store.read("action")
    res = runner.invoke(app, ["record", *_opt(tiny_pusht, "--out", str(store_path), "--episodes", "3", "--seed", "60000")])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output[res.output.index("{"):])
    assert (summary["written"], summary["skipped"]) == (1, 2)
    store = EpisodeStore.open(store_path)
    np.testing.assert_array_equal(store.read("action")[: len(before)], before)

    # another controller's episodes do not join them: one line, nothing written
    res = runner.invoke(app, ["record", str(tiny_pusht["policy"]), "--max-steps", "12", "--out", str(store_path),
                              "--episodes", "4", "--seed", "60000"])
    assert res.exit_code != 0 and "holds data of another kind (collector differ: collector.batch: 2 there, 25 here)" in res.output
    assert "Traceback" not in res.output and EpisodeStore.open(store_path).n_episodes == 3

    # a planner may execute its whole chunk (the true outcome of every action its reward judged), not past it
    res = runner.invoke(app, ["record", *_opt(tiny_pusht, "--out", str(tmp_path / "whole.zarr"), "--episodes", "1",
                                              "--seed", "60000", "--action-steps", "15")])
    assert res.exit_code == 0, res.output
    assert EpisodeStore.open(tmp_path / "whole.zarr").attrs["collector"]["planner"]["action_steps"] == 15
    assert "action_steps" not in store.attrs["collector"]["planner"]  # the policy's, recorded as before the option
    res = runner.invoke(app, ["record", *_opt(tiny_pusht, "--out", str(tmp_path / "past.zarr"), "--action-steps", "16")])
    assert res.exit_code == 2 and "--action-steps 16: must lie in 1..15" in res.output and not (tmp_path / "past.zarr").exists()

    # and a world model trains on them beside the expert's
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT).config, [tiny_pusht["store"], store_path],
               RunConfig(run_dir=tmp_path / "wm", max_steps=2, batch_size=8, progress=False, accelerator="cpu"))
    assert wm.last.exists()


def test_a_bad_out_is_refused_before_any_model_loads(tmp_path):
    """The path alone refuses it: the checkpoints named (here, none there) are never read."""
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    res = runner.invoke(app, ["record", str(tmp_path / "missing.ckpt"), "--planner", "opt", "--world-model",
                              str(tmp_path / "missing-wm.ckpt"), "--out", str(notes)])
    assert res.exit_code == 2 and "notes.txt: is a file, not a store" in res.output and notes.read_text() == "mine"
