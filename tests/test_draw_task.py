"""Triangle Drawing as a gpc task: a layout without objects, the task's own reward on predicted states, the ceiling.

The canvas, expert and explorer have their own tests (tests/test_draw.py); every stage through the CLI runs in
tests/test_reproduce_draw.py. These check what the rest of gpc sees through ``gpc.tasks.get_task("draw")`` alone.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.world_models.config import DynamicsConfig
from gpc.models.world_models.eval_state import per_step_reward
from gpc.tasks import get_task
from gpc.tasks.draw import geometry

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")


def test_nothing_outside_tasks_imports_or_names_the_task():
    named = re.compile(r"""tasks[./]draw|["']draw["']""")
    hits = [f"{path.relative_to(ROOT)}:{i}" for folder in ("gpc", "gpc_cli", "models", "datasets")
            for path in sorted((ROOT / folder).rglob("*.py"))
            for i, line in enumerate(path.read_text().splitlines(), 1) if named.search(line)]
    assert hits == []


def test_a_layout_without_objects_reads_no_goal_and_no_object_frame():
    task = get_task("draw")
    layout = task.layout
    assert layout.objects == () and layout.goal == () and layout.pose_dims == () and "goal" not in task.record_keys(True, "fixed")
    config = DynamicsConfig.for_layout(layout)
    assert config.object_frame == () and config.state_dim == 33 and config.action_target_dims == (0, 1)
    with pytest.raises(ValueError, match="task draw has no object"):
        DynamicsConfig.for_layout(layout, frame="object")
    with pytest.raises(ValueError, match="no object"):
        _ = layout.primary


def _true_states(seed: int, toward: str) -> tuple[np.ndarray, list[float]]:
    """Twelve steps of the pen from its start towards the next vertex (``"edge"``) or the triangle's centre; the
    states after each step and the rewards the environment gave."""
    env = get_task("draw").make_env("fixed")
    env.reset(seed=seed)
    v = env.sim.vertices
    start = int(np.linalg.norm(v - env.sim.pen(), axis=1).argmin())
    goal = v[(start + 1) % 3] if toward == "edge" else v.mean(axis=0)
    states, f1s = [], []
    for target in np.linspace(env.sim.pen(), goal, 12):
        _, reward, *_ = env.step(target)
        states.append(env.sim.state())
        f1s.append(reward)
    return np.array(states), f1s


def test_the_planning_reward_reads_the_ink_from_the_pens_path():
    """The task's own reward (named ``module:function``) takes the first step's ink and draws the rest from the pen's
    path: on true states it is within 0.01 of the environment's F1 at every step, whatever the summaries after the first
    say; it prefers a chunk along the outline to one across the triangle, as the environment does; and it has a
    gradient for GPC-OPT (on the pen, and on the first step's ink: more on the outline is better, more off it worse)."""
    task = get_task("draw")
    reward, discounted = build_reward(RewardSpec(), task), build_reward(RewardSpec(aggregate="discounted"), task)
    along, f1_along = _true_states(100001, "edge")
    across, f1_across = _true_states(100001, "centre")
    assert f1_along[-1] > f1_across[-1] + 0.05  # the environment's verdict
    futures = torch.tensor(np.stack([along, across]), dtype=torch.float32, requires_grad=True)
    score = reward(futures)
    assert score.shape == (2,) and score[0].item() == pytest.approx(f1_along[-1], abs=0.01)
    assert score[1].item() == pytest.approx(f1_across[-1], abs=0.01) and score[0] > score[1] + 0.05
    blind = futures.detach().clone()
    blind[:, 1:, 8:] = blind[:, :1, 8:]  # later summaries that say nothing was drawn: the path still does
    torch.testing.assert_close(reward(blind), score.detach())
    score.sum().backward()
    grad = futures.grad
    assert grad is not None and grad[0, 0, 8:-1].min() > 0 and grad[0, 0, -1] < 0 and grad[:, 1:, :2].abs().sum() > 0
    assert discounted(futures.detach())[0].item() == pytest.approx(sum(0.99**t * f for t, f in enumerate(f1_along)), abs=0.1)
    assert float(geometry.f1_from_summary(along[-1][8:])) == pytest.approx(f1_along[-1], abs=1e-12)
    # one predicted step: the summary's own F1, exactly
    assert reward(futures.detach()[:, -1:])[0].item() == pytest.approx(f1_along[-1], abs=1e-5)
    # `gpc eval world-model` reads, per step, the reward of the future so far, as the planner would: a future whose
    # later summaries say nothing was drawn scores as the true one there too (a state at a time, it scored nothing)
    per_step = per_step_reward(reward, blind)
    torch.testing.assert_close(per_step, per_step_reward(reward, futures.detach()))
    assert per_step[0, -1].item() == pytest.approx(f1_along[-1], abs=0.01) and per_step[0, 0] < per_step[0, -1] - 0.05


def test_a_reader_is_told_every_order_of_the_corners_and_the_reward_is_the_same_on_each():
    """The seed draws which corner comes first (the pen starts there), a frame shows no such order: the task's
    relabelling gives a reader the three cyclic orders (their edges' ink with them) to learn the nearest of, the same
    three whichever the seed drew, and the reward of a path scores each alike."""
    from gpc.models.named import load_named

    task = get_task("draw")
    relabel = load_named(task.layout.state.relabel, "relabel")
    states = torch.tensor(_true_states(100001, "edge")[0], dtype=torch.float32)  # (T, 33), ink growing along an edge
    corners, bins = states[:, 2:8].reshape(-1, 3, 2), states[:, 8:32].reshape(-1, 3, 8)
    turned = [torch.cat([states[:, :2], corners.roll(r, 1).flatten(1), bins.roll(r, 1).flatten(1), states[:, 32:]], 1)
              for r in range(3)]
    options = relabel(states)
    assert options.shape == (len(states), 3, 33) and torch.equal(options[:, 0], states)
    for t in turned:  # the same three labellings, whichever corner the seed drew first
        assert all(any(torch.equal(o, p) for p in relabel(t).unbind(1)) for o in options.unbind(1))
    assert not torch.equal(turned[1], turned[0])
    reward = build_reward(RewardSpec(), task)
    torch.testing.assert_close(reward(options.transpose(0, 1)), reward(states[None]).expand(3))


def test_the_ceiling_replays_the_true_canvas():
    task = get_task("draw")
    env = task.make_env("fixed")
    env.reset(seed=100003)
    obs = task.observe(env, False, True)
    actions = np.linspace(env.sim.pen(), [256.0, 256.0], 6)
    predicted = task.simulator().rollout(torch.as_tensor(obs[task.sim_key])[None, None], torch.as_tensor(actions)[None])
    true = [env.step(action)[0] for action in actions]
    np.testing.assert_allclose(predicted[0].numpy(), np.array(true), rtol=1e-6, atol=1e-4)


def test_the_policys_normaliser_spans_the_ink_off_the_outline_its_demonstrations_barely_make(tmp_path):
    """Real expert episodes on disk: their off-outline ink stays under 0.02, so a span fitted to them alone would put
    one bad chunk's 0.1 at about +10; the task's declared span [0, 1] keeps it near -0.8, and the rest stays fitted."""
    from gpc.datasets.datamodule import EpisodeDataModule
    from gpc.datasets.store import EpisodeStore
    from gpc.models.policy.config import policy_profile
    from gpc.models.policy.module import PolicyModule
    from gpc.models.training.config import RunConfig

    task = get_task("draw")
    store = EpisodeStore.create(tmp_path / "expert.zarr", {"task": "draw"})
    for seed in range(100000, 100006):
        data, _ = task.record("expert", seed, "fixed", False, task.max_episode_steps)
        store.append_episode(data, seed=seed)
    off = geometry.N_SUMMARY + 7
    config = policy_profile("tiny", "state", task.layout).config
    assert config.encoder.state_spans == ((off, 0.0, 1.0),)
    data = EpisodeDataModule(PolicyModule.data_config(config, (str(tmp_path / "expert.zarr"),), RunConfig(tmp_path, max_steps=1), (0, 0.2)))
    states = data.arrays.data["state"]
    assert 0 < states[:, off].max() < 0.02
    norm = data.normalizer
    bad = torch.as_tensor(states[-1]).float().clone()
    bad[off] = 0.1
    assert norm.normalize("state", bad)[off] == pytest.approx(-0.8, abs=1e-5)
    fitted = EpisodeDataModule(dataclasses.replace(data.config, state_spans=())).normalizer
    assert fitted.normalize("state", bad)[off] > 9  # what the policy saw before the span
    torch.testing.assert_close(norm.normalize("state", bad)[:off], fitted.normalize("state", bad)[:off])


def test_a_stores_success_rate_is_the_tasks_not_push_ts(tmp_path):
    """An expert's drawings score just above F1 0.9 (it stops on success): every one succeeded, none reaches 1. Swap's
    success (both objects placed) is no function of its score, so its store's summary gives no rate at all."""
    from faults import inline

    drawn, swapped = tmp_path / "draw.zarr", tmp_path / "swap.zarr"
    assert inline("collect", "--task", "draw", "--out", str(drawn), "--episodes", "2", "--no-images")[0] == 0
    code, out = inline("data", "info", str(drawn), "--json")
    score = json.loads(out)["score"]
    assert code == 0 and score["max"] < 1.0 and score["min"] >= geometry.SUCCESS_F1 and score["success_rate"] == 1.0
    assert inline("collect", "--task", "swap", "--out", str(swapped), "--episodes", "1", "--no-images", "--max-steps", "20")[0] == 0
    code, out = inline("data", "info", str(swapped), "--json")
    assert code == 0 and "mean" in json.loads(out)["score"] and "success_rate" not in json.loads(out)["score"]


def test_a_drawing_scoring_exactly_the_threshold_did_not_succeed():
    """The env's success is an F1 above 0.9; a store's summary must count it the same way, not as Push-T's "at least"."""
    from gpc.tasks import get_task

    scores = np.array([geometry.SUCCESS_F1, np.nextafter(geometry.SUCCESS_F1, 1.0), 0.5])
    assert get_task("draw").succeeded(scores).tolist() == [False, True, False]
    assert get_task("pusht").succeeded(np.array([0.999, 1.0])).tolist() == [False, True]


def test_the_ascent_probe_measures_a_drawing_by_the_pen(tmp_path):
    """No object to register: the probe's world-model error is the pen's distance (it once stacked no outlines)."""
    from faults import inline

    store = tmp_path / "expert.zarr"
    train = ["--task", "draw", "--dataset", str(store), "--profile", "tiny", "--max-steps", "5", "--no-progress"]
    assert inline("collect", "--task", "draw", "--out", str(store), "--episodes", "2", "--no-images")[0] == 0
    assert inline("train", "policy", *train, "--out", str(tmp_path / "policy"))[0] == 0
    assert inline("train", "world-model", *train, "--out", str(tmp_path / "wm"))[0] == 0
    code, out = inline("eval", "ascent", str(tmp_path / "policy" / "checkpoints" / "last.ckpt"), "--planner", "opt", "-M", "2",
                       "--world-model", str(tmp_path / "wm" / "checkpoints" / "last.ckpt"), "--seeds", "200000:200001",
                       "--max-steps", "8", "--out", str(tmp_path / "a.md"))
    assert code == 0, out
    error = json.loads((tmp_path / "a.json").read_text())["model_error"]
    assert np.isfinite(error["start_mean"]) and error["start_mean"] > 0
