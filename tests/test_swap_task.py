"""Cube & Sphere Swapping as a gpc task: the layout, its reward and ceiling, every stage through the CLI, refusals.

The simulator, expert and explorer have their own tests (tests/test_swap.py); these check what the rest of gpc sees
through ``gpc.tasks.get_task("swap")`` alone, and that nothing outside ``tasks/`` names the task.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from faults import inline, one_line
from tiny_planning import shows_the_chosen_future

from gpc.harness.recipes import RewardSpec, build_reward
from gpc.tasks import get_task

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


def test_nothing_outside_tasks_imports_or_names_the_task():
    named = re.compile(r"""tasks[./]swap|["']swap["']""")
    hits = [f"{path.relative_to(ROOT)}:{i}" for folder in ("gpc", "gpc_cli", "models", "datasets")
            for path in sorted((ROOT / folder).rglob("*.py"))
            for i, line in enumerate(path.read_text().splitlines(), 1) if named.search(line)]
    assert hits == []


def test_the_layout_observes_a_goal_per_episode_and_the_reward_compares_positions():
    task = get_task("swap")
    layout = task.layout
    assert [o.name for o in layout.objects] == ["cube", "sphere"] and layout.goal is None and layout.pose_dims == (2, 3, 5, 6)
    assert task.row_shape("goal") == (4,) and "goal" in task.record_keys(False, "fixed")
    reward = build_reward(RewardSpec(), task)
    goal = torch.tensor([[300.0, 200.0, 120.0, 400.0]] * 3)
    states = torch.tensor([[[50.0, 50.0, 300.0, 200.0, 0.3, 120.0, 400.0]],  # both on target, the cube turned
                           [[50.0, 50.0, 310.0, 200.0, 0.0, 120.0, 400.0]],  # the cube 10 px off
                           [[50.0, 50.0, 300.0, 200.0, 0.0, 120.0, 430.0]]])  # the sphere 30 px off
    assert reward(states, goal).tolist() == pytest.approx([0.0, -5.0, -15.0], abs=1e-3)


def test_the_ceiling_replays_the_true_simulator():
    """gt-sim's world model predicts exactly what the environment does with the same actions."""
    task = get_task("swap")
    env = task.make_env("fixed")
    env.reset(seed=100003)
    obs = task.observe(env, False, True)
    actions = np.linspace(env.sim.state()[:2], [256.0, 256.0], 6)
    predicted = task.simulator().rollout(torch.as_tensor(obs[task.sim_key])[None, None], torch.as_tensor(actions)[None])
    true = []
    for action in actions:
        env.step(action)
        true.append(env.sim.state())
    np.testing.assert_allclose(predicted[0].numpy(), np.array(true), atol=1e-3)


def test_every_stage_runs_from_the_cli_and_refuses_another_tasks_files(tmp_path):
    store, explore, pushed = tmp_path / "expert.zarr", tmp_path / "explore.zarr", tmp_path / "pusht.zarr"
    train = ["--profile", "tiny", "--max-steps", "10", "--no-progress"]
    assert inline("collect", "--task", "swap", "--out", str(store), "--episodes", "3", "--no-images")[0] == 0
    assert inline("collect", "--task", "swap", "--explore", "--out", str(explore), "--episodes", "2", "--seed", "50000",
                  "--no-images", "--max-steps", "60")[0] == 0
    assert inline("train", "policy", "--task", "swap", "--dataset", str(store), "--out", str(tmp_path / "policy"), *train)[0] == 0
    assert inline("train", "world-model", "--task", "swap", "--dataset", str(store), "--dataset", str(explore),
                  "--out", str(tmp_path / "wm"), *train)[0] == 0
    policy, wm = tmp_path / "policy" / "checkpoints" / "last.ckpt", tmp_path / "wm" / "checkpoints" / "last.ckpt"
    code, out = inline("inspect", str(policy), "--json")
    assert code == 0 and json.loads(out)["observations"] == {"state": [7], "goal": [4]}  # it reads each episode's targets
    seeds = ["--seeds", "100000:100002", "--max-steps", "16"]
    planners = {"bc": [], "rank": ["--planner", "rank", "-K", "4", "--world-model", str(wm)],
                "opt": ["--planner", "opt", "-M", "2", "--world-model", str(wm)], "ceiling": ["--planner", "gt-sim", "-K", "4"]}
    labels = {"bc": ("bc", None), "rank": ("rank K=4", str(wm)), "opt": ("opt M=2", str(wm)), "ceiling": ("gt-sim K=4", "gt-sim")}
    for name, planner in planners.items():
        assert inline("eval", str(policy), *planner, *seeds, "--out", str(tmp_path / name))[0] == 0
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        assert summary["config"]["task"] == "swap" and len(json.loads((tmp_path / name / "episodes.json").read_text())) == 2
        controller = summary["run"]["controller"]  # each option reached the planner, not only the folder name
        assert (controller["controller"], controller.get("world_model")) == labels[name], controller
        assert summary["config"]["seeds"] == [100000, 100001]
    # `gpc plan`: swap draws no futures of its own, so the chosen candidate's predicted state is drawn beside the scene
    assert inline("plan", str(policy), "--world-model", str(wm), "-K", "3", "--seed", "100001", "--max-steps", "8",
                  "--out", str(tmp_path / "plan"))[0] == 0
    assert shows_the_chosen_future(tmp_path / "plan" / "seed100001.mp4")
    # another task's store, policy or world model: one line naming both tasks, nothing written
    assert inline("collect", "--out", str(pushed), "--episodes", "1", "--no-images", "--max-steps", "30")[0] == 0
    one_line(inline("train", "world-model", "--task", "swap", "--dataset", str(pushed), "--out", str(tmp_path / "mixed"), *train), 2,
             str(pushed), "task pusht, not of task swap")
    one_line(inline("eval", str(policy), "--task", "pusht", "--planner", "rank", "-K", "2", "--world-model", str(wm), *seeds,
                    "--out", str(tmp_path / "mixed")), 2)
    assert inline("train", "policy", "--dataset", str(pushed), "--out", str(tmp_path / "pusht-policy"), *train)[0] == 0
    one_line(inline("eval", str(tmp_path / "pusht-policy" / "checkpoints" / "last.ckpt"), "--planner", "rank", "-K", "2",
                    "--world-model", str(wm), *seeds, "--out", str(tmp_path / "mixed")), 2, "task 'swap', expected task 'pusht'")
    assert not (tmp_path / "mixed").exists()


def test_a_store_without_goals_is_described_without_scores(tmp_path):
    """`gpc eval ranking --save-replays` keeps states and actions only: swap cannot score them, the rest is described."""
    from gpc.datasets.store import EpisodeStore

    task = get_task("swap")
    store = EpisodeStore.create(tmp_path / "replays.zarr", {"task": "swap"})
    data, _ = task.record("expert", 100000, "fixed", False, 12)
    store.append_episode({k: data[k] for k in ("state", "action")}, seed=100000)
    code, out = inline("data", "info", str(tmp_path / "replays.zarr"), "--json")
    info = json.loads(out)
    assert code == 0 and info["steps"] == 12 and "score" not in info and "data/goal" in info["score_note"]
