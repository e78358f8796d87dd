"""Planners over real (tiny) trained policy and world model checkpoints and the real simulator."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from tiny_planning import PUSHT, gens, histories, planner
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.harness.comparison import paired_interval, t_quantile
from gpc.harness.recipes import PlannerRecipe, RewardSpec, build_reward
from gpc.models.planning.ascent import ascend
from gpc.models.planning.config import PLANNERS, PlannerConfig
from gpc.models.planning.loading import load_planner
from gpc.models.planning.objective import Objective, PartTimer
from gpc.models.planning.planner import model_planner
from gpc.models.policy.controller import PolicyController
from gpc.models.policy.module import PolicyModule
from gpc.models.rewards.registration import RegistrationReward
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks.pusht import LAYOUT, SimulatorModel
from gpc.tasks.pusht.env import PushTEnv
from gpc.tasks.pusht.record import observe


@pytest.mark.parametrize("kind,k,m", [("rank", 6, 0), ("opt", 1, 3), ("rank-opt", 3, 3), ("cem", 8, 2),
                                      ("mppi", 8, 2), ("grad", 3, 2)])
def test_every_planner_returns_valid_chunks(ckpts, kind, k, m):
    assert kind in PLANNERS
    p = planner(ckpts, kind=kind, num_proposals=k, opt_steps=m, keep_futures=True)
    seeds = (100000, 100001)
    plan = p.plan(histories(seeds), gens(seeds))
    assert plan.actions.shape == (2, p.n_action_steps, 2) and plan.chunk.shape == (2, p.horizon, 2)
    assert np.isfinite(plan.chunk).all() and plan.chunk.min() >= 0 and plan.chunk.max() <= 512
    np.testing.assert_array_equal(plan.actions, plan.chunk[:, : p.n_action_steps])
    assert plan.futures.shape[:3] == plan.scores.shape + (p.horizon,)
    best = plan.scores[np.arange(2), plan.chosen]
    assert np.all(best == plan.scores.max(axis=1))
    np.testing.assert_allclose(plan.candidates[np.arange(2), plan.chosen], plan.chunk)
    assert set(plan.seconds) >= {"world_model", "reward"}


def test_a_planner_may_execute_its_whole_chunk(ckpts):
    """``action_steps``: the actions run per decision, the policy's n_action_steps unless given, at most the chunk."""
    seeds = (100000, 100001)
    one = {"kind": "opt", "num_proposals": 1, "opt_steps": 2}
    default, whole = planner(ckpts, **one), planner(ckpts, **one, action_steps=15)
    assert default.n_action_steps == 8 and whole.n_action_steps == whole.horizon == 15
    plan = whole.plan(histories(seeds), gens(seeds))
    np.testing.assert_array_equal(plan.actions, plan.chunk)
    with pytest.raises(ValueError, match="--action-steps 16: must lie in 1..15"):
        planner(ckpts, **one, action_steps=16)


def test_rank_with_one_proposal_is_behaviour_cloning(ckpts):
    seeds = (100000, 100001, 100002)
    obs = histories(seeds)
    bc = PolicyController(PolicyModule.load_from_checkpoint(ckpts["policy"])).plan(obs, gens(seeds))
    rank = planner(ckpts, kind="rank", num_proposals=1).plan(obs, gens(seeds))
    np.testing.assert_array_equal(rank.chunk, bc.chunk)
    np.testing.assert_array_equal(rank.actions, bc.actions)


def test_rank_opt_batched_equals_one_by_one(ckpts):
    p = planner(ckpts, kind="rank-opt", num_proposals=4, opt_steps=5, lr=3.0)
    seeds = (100000, 100001)
    obs = histories(seeds)
    together = p.plan(obs, gens(seeds))
    for b, seed in enumerate(seeds):  # each history alone
        alone = p.plan({k: v[b : b + 1] for k, v in obs.items()}, gens((seed,)))
        np.testing.assert_allclose(alone.chunk[0], together.chunk[b], atol=1e-3)
        np.testing.assert_allclose(alone.scores[0], together.scores[b], atol=1e-3)
    # and each candidate optimised on its own (K = 1 per call) equals the batch of K
    history = torch.as_tensor(obs["state"][:1])
    init = p.policy.sample_batch({k: v[:1] for k, v in obs.items()}, 4, gens(seeds[:1]))[:, :, p.now :]
    objective = Objective(p.world_model, p.reward, history, None, PartTimer())
    batch = ascend(objective, init, p.config, PartTimer())[0]
    for k in range(4):
        single = ascend(objective, init[:, k : k + 1], p.config, PartTimer())[0]
        np.testing.assert_allclose(single[0, 0].numpy(), batch[0, k].numpy(), atol=1e-3)


def test_ground_truth_predictions_are_what_the_simulator_delivers(ckpts):
    """The gt-sim planner's predicted rewards equal those the episode's own scene then produces."""
    reward = build_reward(RewardSpec(), PUSHT)
    p = model_planner(PlannerConfig(kind="rank", num_proposals=8, keep_futures=True), SimulatorModel(), reward,
                PolicyModule.load_from_checkpoint(ckpts["policy"]))
    for seed in (100000, 100003):
        env = PushTEnv()
        env.reset(seed=seed)
        for _ in range(5):  # push the block around first so contacts are live at the decision
            env.step(env.sim.state()[2:4])
        o = observe(env, images=False, sim=True)
        plan = p.plan({k: np.stack([v, v])[None] for k, v in o.items()}, gens((seed,)))
        predicted = plan.futures[0, plan.chosen[0]]
        states = []
        for action in plan.chunk[0]:
            env.step(action)
            states.append(env.sim.state())
        states = torch.as_tensor(np.array(states), dtype=torch.float32)[None]
        delivered = reward(states)
        assert float(delivered[0]) == pytest.approx(float(plan.scores[0, plan.chosen[0]]), abs=0.05)
        np.testing.assert_allclose(reward.per_step(states)[0], reward.per_step(torch.as_tensor(predicted)[None])[0], atol=0.05)


def test_deployment_api_acts_on_one_history(ckpts):
    """The README's example: checkpoints + a reward -> ``act(obs_history)``, no simulator."""
    reward = RegistrationReward(torch.tensor(LAYOUT.primary.vertices), torch.tensor([256.0, 256.0, np.pi / 4]), LAYOUT.pose_dims)
    p = load_planner(ckpts["policy"], ckpts["wm"], reward, PlannerConfig(kind="rank-opt", num_proposals=3, opt_steps=2))
    obs = {k: v[0] for k, v in histories((100000,)).items()}
    chunk = p.act(obs, torch.Generator().manual_seed(0))
    again = p.act(obs, torch.Generator().manual_seed(0))
    assert chunk.shape == (p.horizon, 2)
    np.testing.assert_array_equal(chunk, again)


def test_paired_statistics():
    assert t_quantile(0.975, 9) == pytest.approx(2.262, abs=2e-3)
    assert t_quantile(0.975, 99) == pytest.approx(1.984, abs=1e-3)
    mean, lo, hi = paired_interval(np.array([0.1, 0.2, 0.3, 0.0, 0.1]))
    assert mean == pytest.approx(0.14) and lo < mean < hi and hi - mean == pytest.approx(mean - lo)


def test_cli_eval_plan_and_compare(ckpts, tmp_path):
    runner, base = CliRunner(), ["--seeds", "100000:100003", "--max-steps", "16", "--batch", "3"]
    res = runner.invoke(app, ["eval", ckpts["policy"], *base, "--out", str(tmp_path / "bc")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["eval", ckpts["policy"], "--planner", "rank", "--world-model", ckpts["wm"], "-K", "4",
                              *base, "--out", str(tmp_path / "rank")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["eval", ckpts["policy"], "--planner", "gt-sim", "-K", "4", *base, "--out", str(tmp_path / "gt")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "rank" / "summary.json").read_text())
    assert summary["controller"]["controller"] == "rank K=4" and set(summary["time_share"]) >= {"policy", "world_model"}
    res = runner.invoke(app, ["compare", str(tmp_path / "rank"), str(tmp_path / "gt"), "--baseline", str(tmp_path / "bc"),
                              "--ceiling", str(tmp_path / "gt"), "--out", str(tmp_path / "cmp.md"), "--paper", "pusht-state"])
    assert res.exit_code == 0, res.output
    table = json.loads((tmp_path / "cmp.json").read_text())
    assert (tmp_path / "cmp.png").stat().st_size > 1000
    assert [r["label"] for r in table["rows"]] == ["bc", "rank K=4", "gt-sim K=4"]
    assert table["rows"][0]["score_diff"] == 0.0
    # More seeds later: a second range joined with '+' equals one run over both ranges (same lockstep groups).
    for name, seeds in (("bc-more", "100003:100005"), ("bc-all", "100000:100005")):
        res = runner.invoke(app, ["eval", ckpts["policy"], "--seeds", seeds, "--max-steps", "16", "--batch", "3",
                                  "--out", str(tmp_path / name)])
        assert res.exit_code == 0, res.output
    joined = f"{tmp_path / 'bc'}+{tmp_path / 'bc-more'}"
    res = runner.invoke(app, ["compare", joined, "--baseline", str(tmp_path / "bc-all"), "--out", str(tmp_path / "j.md")])
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "j.json").read_text())["rows"]
    assert rows[1]["seeds"] == 5 and rows[1]["score"] == rows[0]["score"] and rows[1]["score_diff"] == 0.0
    assert rows[0]["label"] == "bc" and rows[1]["label"] == f"bc ({tmp_path.name})"  # one controller twice: told apart
    res = runner.invoke(app, ["compare", f"{tmp_path / 'bc'}+{tmp_path / 'bc-all'}", "--baseline", str(tmp_path / "bc-all"),
                              "--out", str(tmp_path / "k.md")])
    assert res.exit_code != 0 and "appear in more than one part" in res.output and "Traceback" not in res.output
    guarded = ["--planner", "rank-opt", "-K", "2", "-M", "3", "--world-model", ckpts["wm"], "--lr-decay", "cosine",
               "--trust-region", "4", "--keep-best", "--knots", "4"]
    res = runner.invoke(app, ["eval", ckpts["policy"], *guarded, *base, "--out", str(tmp_path / "guarded")])
    assert res.exit_code == 0, res.output
    planner_settings = json.loads((tmp_path / "guarded" / "summary.json").read_text())["run"]["controller"]["planner"]
    assert (planner_settings["lr_decay"], planner_settings["trust_region"], planner_settings["keep_best"],
            planner_settings["knots"]) == ("cosine", 4.0, True, 4)
    res = runner.invoke(app, ["plan", ckpts["policy"], "--world-model", ckpts["wm"], "-K", "3", "--seed", "100001",
                              "--max-steps", "16", "--out", str(tmp_path / "plan")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "plan" / "seed100001.mp4").stat().st_size > 1000
    # a video there that gpc did not write is refused before any work, and the results beside it are kept
    (tmp_path / "plan" / "seed100002.mp4").write_bytes(b"mine")
    before = (tmp_path / "plan" / "summary.json").read_bytes()
    res = runner.invoke(app, ["plan", ckpts["policy"], "--world-model", ckpts["wm"], "-K", "3", "--seed", "100002",
                              "--max-steps", "16", "--out", str(tmp_path / "plan"), "--overwrite"])
    assert res.exit_code == 2 and "seed100002.mp4: exists and was not written by gpc" in res.output
    assert (tmp_path / "plan" / "summary.json").read_bytes() == before and (tmp_path / "plan" / "seed100002.mp4").read_bytes() == b"mine"


def test_compare_tells_apart_runs_of_one_controller():
    from gpc.harness.comparison import _tell_apart

    rows = [{"label": "bc", "path": "r/a/bc"}, {"label": "rank K=8", "path": "r/a/rank"}, {"label": "rank K=8", "path": "r/b/rank"},
            {"label": "opt M=5", "path": "r/a/opt"}, {"label": "opt M=5", "path": "r/a/opt-wm2+r/c/opt-wm2"}]
    _tell_apart(rows)  # by results folder; by the run's own folder where they share the results folder
    assert [r["label"] for r in rows] == ["bc", "rank K=8 (a)", "rank K=8 (b)", "opt M=5 (opt)", "opt M=5 (opt-wm2)"]


@pytest.mark.parametrize("args,expect", [
    (["--planner", "opt", "-K", "5"], "--K 5: opt refines one proposal"),
    (["--planner", "rank"], "--planner rank needs --world-model"),
    (["--planner", "grad", "--world-model", "gt-sim"], "gt-sim is not differentiable"),
    (["--planner", "rank", "--world-model", "WM", "-K", "0"], "--K 0: must lie in"),
    (["--planner", "zigzag", "--world-model", "WM"], "--planner 'zigzag'"),
    (["--planner", "rank", "--world-model", "POLICY"], "is a 'policy' checkpoint, expected a 'world_model'"),
    (["--planner", "rank", "--world-model", "WM", "--keep-best"], "--knots apply to opt, rank-opt, grad, not --planner rank"),
    (["--planner", "opt", "--world-model", "WM", "--knots", "-1"], "Invalid value for '--knots'"),
    (["--planner", "opt", "--world-model", "WM", "--knots", "99"], "--knots 99: at most"),
    (["--trust-region", "5"], "not --planner bc"),
    (["--action-steps", "4"], "--action-steps apply to a --planner (bc is the policy alone)"),
    (["--planner", "rank", "--world-model", "WM", "--action-steps", "0"], "Invalid value for '--action-steps'"),
    (["--planner", "opt", "--world-model", "WM", "--trust-region", "-1"], "--trust-region -1.0: must be a finite number >= 0"),
    (["--planner", "opt", "--world-model", "WM", "--lr-decay", "linear"], "--lr-decay 'linear': use one of constant, cosine"),
])
def test_cli_bad_planner_options_fail_in_one_line(ckpts, tmp_path, args, expect):
    args = [{"WM": ckpts["wm"], "POLICY": ckpts["policy"]}.get(a, a) for a in args]
    res = CliRunner().invoke(app, ["eval", ckpts["policy"], *args, "--seeds", "100000", "--out", str(tmp_path / "o")])
    assert res.exit_code != 0
    assert expect in res.output and "Traceback" not in res.output
    assert len(res.output.strip().splitlines()) == 1, res.output


def test_world_model_of_another_task_is_refused(ckpts, tmp_path):
    ckpt = torch.load(ckpts["wm"], weights_only=True)
    ckpt["gpc"]["task"] = "other"
    ckpt["hyper_parameters"]["config"]["task"] = "other"
    torch.save(ckpt, tmp_path / "other.ckpt")
    res = CliRunner().invoke(app, ["eval", ckpts["policy"], "--planner", "rank", "--world-model", str(tmp_path / "other.ckpt"),
                                   "--seeds", "100000", "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "task" in res.output and "Traceback" not in res.output


def test_recipe_is_picklable_and_labels(ckpts):
    import pickle

    recipe = PlannerRecipe(ckpts["policy"], PlannerConfig(kind="rank", num_proposals=7), "gt-sim")
    assert pickle.loads(pickle.dumps(recipe)).label == "gt-sim K=7"
    assert dataclasses.replace(recipe, planner=None, world_model=None).label == "bc"
    assert len(LAYOUT.primary.vertices) == 8


def test_cli_rank_with_a_vlm_reward_against_a_loopback_server(ckpts, tmp_path):
    """`gpc eval --planner rank --reward vlm`: real HTTP, one query per decision, fallbacks counted, cache reused."""
    from benchmarks.vlm_server import Reply, ScriptedChatServer

    args = ["eval", ckpts["policy"], "--planner", "rank", "--world-model", ckpts["wm"], "-K", "3", "--reward", "vlm",
            "--vlm-model", "scripted-vl", "--seeds", "100000:100002", "--max-steps", "24", "--batch", "2",
            "--out", str(tmp_path / "vlm")]
    with ScriptedChatServer([Reply("2"), Reply("candidate two, I think")]) as server:
        res = CliRunner().invoke(app, args + ["--vlm-base-url", server.base_url])
        assert res.exit_code == 0, res.output
        decisions = 2 * 3  # two episodes, 24 steps in chunks of 8
        assert len(server.requests) == decisions
        assert server.requests[0].body["temperature"] == pytest.approx(0.2)
        assert len(server.requests[0].images()) == 1
        stats = json.loads((tmp_path / "vlm" / "summary.json").read_text())["controller_stats"]
        assert stats["queries"] == decisions and stats["fell_back"] == decisions - 1
        assert stats["fallbacks"]["malformed"] == decisions - 1
        assert "fell back: 5 of 6" in (tmp_path / "vlm" / "summary.md").read_text()
        again = CliRunner().invoke(app, args + ["--vlm-base-url", server.base_url, "--overwrite"])
        assert again.exit_code == 0, again.output
        assert len(server.requests) == decisions  # every answer came from the cache
    res = CliRunner().invoke(app, args[:-2] + ["--out", str(tmp_path / "v2")])
    assert res.exit_code != 0 and "--vlm-base-url" in res.output


PLAIN_PYTHON = """
import sys, json
from gpc.harness.evaluation import EvalConfig, evaluate
from gpc.models.planning.config import PlannerConfig
from gpc.models.planning.planner import Planner, model_planner
from gpc.models.policy.module import PolicyModule
from gpc.models.rewards.registration import RegistrationReward
from gpc.models.world_models.module import WorldModelModule
from gpc.tasks import get_task

policy_ckpt, wm_ckpt = sys.argv[1:3]
layout = get_task("pusht").layout
planner = model_planner(PlannerConfig(kind="rank", num_proposals=4), WorldModelModule.load_from_checkpoint(wm_ckpt),
                  RegistrationReward.from_layout(layout), PolicyModule.load_from_checkpoint(policy_ckpt))
result = evaluate(lambda: planner, EvalConfig(seeds=(100000, 100001), task="pusht", max_steps=16, batch=2))
print(json.dumps({"score": result["mean_score"], "shares": sorted(result["time_share"]),
                  "cli": sorted(m for m in sys.modules if m.startswith("gpc.cli") or m.split(".")[0] in ("typer", "click"))}))
"""


def test_a_planner_built_in_plain_python_runs_closed_loop_without_the_cli(ckpts, tmp_path):
    """The library alone: a planner assembled from its parts and the harness; neither gpc.cli nor Typer is imported."""
    import subprocess
    import sys

    script = tmp_path / "plan.py"
    script.write_text(PLAIN_PYTHON)
    out = subprocess.run([sys.executable, str(script), ckpts["policy"], ckpts["wm"]], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["cli"] == [] and 0.0 <= report["score"] <= 1.0
    assert report["shares"] == ["policy", "reward", "world_model"]


def test_load_planner_refuses_a_world_model_of_the_other_family(ckpts, tmp_path):
    """The pairing check lives in the library: a visual world model cannot plan for a keypoint policy."""
    from gpc.datasets.errors import DataError
    from gpc.datasets.normalizer import MinMaxNormalizer
    from gpc.models.training.checkpoint import checkpoint_meta

    visual = WorldModelModule(world_model_profile("tiny", 1, LAYOUT, obs="image").config, normalizer=MinMaxNormalizer())
    path = tmp_path / "visual.ckpt"
    torch.save({"gpc": checkpoint_meta("world_model", "pusht", obs="image", phase=1), "state_dict": visual.state_dict(),
                "hyper_parameters": dict(visual.hparams)}, path)
    with pytest.raises(DataError, match="a visual world model cannot plan for a keypoints policy"):
        load_planner(ckpts["policy"], path, RegistrationReward.from_layout(LAYOUT))
