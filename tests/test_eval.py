"""The closed-loop harness: real simulator, a real (tiny) trained policy, numbers asserted."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.harness.collection import CollectJob, collect
from gpc.harness.evaluation import EvalConfig, episode_generator, evaluate, run_group, write_results
from gpc.harness.recipes import PlannerRecipe
from gpc.models.planning.protocols import Controller, Plan
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.tasks.pusht import LAYOUT, geometry
from gpc.tasks.pusht.env import PushTEnv

SEEDS = (100000, 100001, 100002, 100003)


@dataclass(frozen=True)
class HoldStill:
    """Targets the agent's own position: nothing moves, so every number is known in advance."""

    obs_keys: tuple[str, ...] = ("state",)
    n_obs_steps: int = 2

    def __call__(self) -> HoldStill:
        return self

    def plan(self, obs, generators) -> Plan:
        agent = obs["state"][:, -1, :2].astype(np.float64)
        chunk = np.repeat(agent[:, None], 8, axis=1)
        return Plan(actions=chunk[:, :4], chunk=chunk, seconds={"policy": 0.0})


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> str:
    """A keypoint policy trained a few steps on real expert demonstrations."""
    tmp = tmp_path_factory.mktemp("eval")
    collect(CollectJob(task="pusht", out=tmp / "expert.zarr", episodes=3, images=False, max_steps=60))
    result = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [tmp / "expert.zarr"],
                          RunConfig(run_dir=tmp / "run", max_steps=30, batch_size=32, progress=False, accelerator="cpu"))
    return str(result.last)


def test_harness_scores_a_known_controller_exactly():
    assert isinstance(HoldStill(), Controller)
    res = evaluate(HoldStill(), EvalConfig(task="pusht", seeds=SEEDS, max_steps=20, batch=3))
    for row in res["episodes"]:
        env = PushTEnv()
        _, info = env.reset(seed=row["seed"])
        assert row["steps"] == 20 and not row["success"]
        assert row["score"] == pytest.approx(geometry.reward_from_coverage(info["coverage"]), abs=1e-6)
    assert res["mean_score"] == pytest.approx(np.mean([r["score"] for r in res["episodes"]]))
    assert res["call_latency_s"]["p50"] >= 0 and res["wall_s"] > 0


def test_bc_results_are_identical_for_any_worker_count_and_repeatable(checkpoint, tmp_path):
    factory = PlannerRecipe(str(checkpoint))  # BC: the policy alone
    config = EvalConfig(task="pusht", seeds=SEEDS, max_steps=24, batch=2)
    one = evaluate(factory, config)
    two = evaluate(factory, EvalConfig(task="pusht", seeds=SEEDS, max_steps=24, batch=2, workers=2))
    again = evaluate(factory, config)
    assert one["episodes"] == two["episodes"] == again["episodes"]
    assert [r["seed"] for r in one["episodes"]] == list(SEEDS)
    other = evaluate(factory, EvalConfig(task="pusht", seeds=SEEDS, max_steps=24, batch=2, sampling_seed=1))
    assert other["episodes"] != one["episodes"]  # the sampling seed does reach the policy
    write_results(one, tmp_path / "out", "BC")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["mean_score"] == one["mean_score"]
    assert "| 100000..100003 (4) |" in (tmp_path / "out" / "summary.md").read_text()


class EndsEarly(PushTEnv):
    """Push-T whose episode of seed s ends (as a success) after 4 (s - 100000) + 3 steps: groups finish unevenly."""

    def reset(self, seed=None, options=None):
        self.left = 4 * (seed - 100000) + 3
        return super().reset(seed=seed, options=options)

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        self.left -= 1
        return obs, reward, terminated or self.left <= 0, truncated, info


class Sizes:
    """HoldStill that keeps the episodes it is told of and the batch of every call."""

    obs_keys, n_obs_steps = HoldStill.obs_keys, HoldStill.n_obs_steps

    def __init__(self) -> None:
        self.told: list[list[int]] = []
        self.batches: list[int] = []

    def start(self, episodes) -> None:
        self.told.append(list(episodes))

    def plan(self, obs, generators) -> Plan:
        assert len(generators) == obs["state"].shape[0]
        self.batches.append(obs["state"].shape[0])
        return HoldStill().plan(obs, generators)


def test_finished_episodes_are_not_planned_for_and_results_do_not_change(checkpoint, monkeypatch):
    import gpc.harness.evaluation as evaluation

    task = evaluation.get_task("pusht")
    monkeypatch.setattr(evaluation, "get_task", lambda name: replace(task, make_env=lambda goal: EndsEarly()))
    sizes = Sizes()
    res = run_group(sizes, SEEDS, EvalConfig(task="pusht", seeds=SEEDS, max_steps=20, batch=4))
    assert [r["steps"] for r in res["episodes"]] == [3, 7, 11, 15] and all(r["success"] for r in res["episodes"])
    assert sizes.batches == [4, 3, 2, 1] and res["call_sizes"] == sizes.batches  # 4 actions a call
    assert sizes.told == [list(SEEDS), list(SEEDS[1:]), list(SEEDS[2:]), list(SEEDS[3:])]
    # A real policy's episodes in one uneven group are each one's alone, up to the float rounding of a batch size.
    factory = PlannerRecipe(str(checkpoint))
    together = evaluate(factory, EvalConfig(task="pusht", seeds=SEEDS, max_steps=20, batch=4))["episodes"]
    alone = evaluate(factory, EvalConfig(task="pusht", seeds=SEEDS, max_steps=20, batch=1))["episodes"]
    assert [r["steps"] for r in together] == [r["steps"] for r in alone] == [3, 7, 11, 15]
    for a, b in zip(together, alone):
        assert a["final_state"] == pytest.approx(b["final_state"], abs=1e-2)


def test_episode_streams_are_independent_of_batch_layout():
    a = torch.randn(3, generator=episode_generator(0, 100007))
    b = torch.randn(3, generator=episode_generator(0, 100007))
    c = torch.randn(3, generator=episode_generator(0, 100008))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_eval_cli_writes_summary_and_video(checkpoint, tmp_path):
    res = CliRunner().invoke(app, ["eval", checkpoint, "--seeds", "100000:100002", "--max-steps", "16",
                                   "--out", str(tmp_path), "--videos", "1", "--steps", "2"])
    spread = CliRunner().invoke(app, ["eval", checkpoint, "--seeds", "100000:100002", "--max-steps", "8",
                                      "--out", str(tmp_path / "spread"), "--sampling-seeds", "0,1"])
    assert spread.exit_code == 0, spread.output
    agg = json.loads((tmp_path / "spread" / "summary.json").read_text())
    assert agg["sampling_seeds"] == [0, 1] and len(agg["mean_scores"]) == 2
    assert (tmp_path / "spread" / "sampling-seed-1" / "episodes.json").exists()
    assert res.exit_code == 0, res.output
    episodes = json.loads((tmp_path / "episodes.json").read_text())
    assert [e["seed"] for e in episodes] == [100000, 100001] and all(e["steps"] == 16 for e in episodes)
    cap = cv2.VideoCapture(str(tmp_path / "videos" / "seed100000.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 16
    assert not (tmp_path / "videos" / "seed100001.mp4").exists()


@pytest.mark.parametrize("make, expect", [("missing", "no such"), ("garbage", "checkpoint")])
def test_eval_cli_rejects_bad_checkpoints_in_one_line(tmp_path, make, expect):
    ckpt = tmp_path / "policy.ckpt"
    if make == "garbage":
        ckpt.write_bytes(b"not a checkpoint")
    res = CliRunner().invoke(app, ["eval", str(ckpt), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and expect in lines[0].lower()
    assert not (tmp_path / "o").exists()


@dataclass
class Recorder:
    """Drives the agent towards a far corner and keeps every observation history it is handed."""

    obs_keys: tuple[str, ...] = ("state",)
    n_obs_steps: int = 2

    def __post_init__(self) -> None:
        self.seen: list[np.ndarray] = []

    def plan(self, obs, generators) -> Plan:
        self.seen.append(obs["state"].copy())
        chunk = np.tile(np.array([450.0, 450.0]), (obs["state"].shape[0], 8, 1))
        return Plan(actions=chunk, chunk=chunk)


def test_history_holds_consecutive_steps_like_the_training_windows():
    """Diffusion Policy conditions on o_{t-1}, o_t; a history of o_{t-8}, o_t halves the scores (measured)."""
    recorder = Recorder()
    run_group(recorder, (100000,), EvalConfig(task="pusht", seeds=(100000,), max_steps=16, batch=1))
    env = PushTEnv()
    env.reset(seed=100000)
    states = [env.sim.state()]
    for _ in range(8):
        env.step(np.array([450.0, 450.0]))
        states.append(env.sim.state())
    np.testing.assert_allclose(recorder.seen[0][0], np.stack([states[0], states[0]]), atol=1e-4)
    np.testing.assert_allclose(recorder.seen[1][0], np.stack([states[7], states[8]]), atol=1e-4)


def test_random_goal_pipeline_collects_trains_and_plans_towards_each_episodes_goal(tmp_path, monkeypatch):
    """GPC's random-goal variant: the stores, the policy and the planners all see each episode's goal."""
    runner = CliRunner()
    store = tmp_path / "expert.zarr"
    collect(CollectJob(task="pusht", out=store, episodes=2, images=False, max_steps=30, goal="random"))
    trained = runner.invoke(app, ["train", "policy", "--dataset", str(store), "--obs", "keypoints", "--goal", "random",
                                  "--profile", "tiny", "--max-steps", "2", "--batch-size", "8", "--accelerator", "cpu",
                                  "--no-progress", "--out", str(tmp_path / "run")])
    assert trained.exit_code == 0, trained.output
    ckpt = str(tmp_path / "run" / "checkpoints" / "last.ckpt")
    from gpc.models.policy.module import PolicyModule

    policy = PolicyModule.load_from_checkpoint(ckpt)
    assert dict(policy.config.encoder.obs_shapes)["goal_keypoint"] == (9, 2)

    seen: list[np.ndarray] = []
    from gpc.models.rewards.registration import RegistrationReward

    original = RegistrationReward.forward
    monkeypatch.setattr(RegistrationReward, "forward",
                        lambda self, futures, goal=None: (seen.append(goal.clone()), original(self, futures, goal))[1])
    res = runner.invoke(app, ["eval", ckpt, "--planner", "gt-sim", "-K", "2", "--goal", "random",
                              "--seeds", "100000:100002", "--max-steps", "8", "--out", str(tmp_path / "eval")])
    assert res.exit_code == 0, res.output
    goals = {tuple(np.round(g.numpy(), 3).tolist()) for batch in seen for g in batch}
    expected = {tuple(np.round(PushTEnv(goal="random").reset(seed=s)[1]["goal_pose"].astype(np.float32), 3).tolist())
                for s in (100000, 100001)}
    assert goals == expected  # each candidate is scored against its own episode's goal, not the fixed one
    fixed = runner.invoke(app, ["eval", ckpt, "--seeds", "100000:100002", "--out", str(tmp_path / "fixed")])
    lines = [line for line in fixed.output.splitlines() if line.strip()]
    assert fixed.exit_code == 2 and len(lines) == 1 and "--goal random" in lines[0], fixed.output
