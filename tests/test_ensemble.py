"""World-model ensembles: one checkpoint from several, every member's future scored, disagreement doubted."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_cli import gpc
from tiny_planning import PUSHT, gens, histories, train_checkpoints

from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.planning.config import PlannerConfig
from gpc.models.planning.loading import load_planner
from gpc.models.planning.objective import ModelScorer, Objective, PartTimer
from gpc.models.planning.planner import model_planner
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.ensemble import WorldModelEnsemble, load_any
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks.pusht import LAYOUT

pytestmark = pytest.mark.usefixtures("one_thread")
RUN = dict(batch_size=32, progress=False, accelerator="cpu")


def _wm(tmp: Path, name: str, seed: int, history: int | None = None) -> str:
    config = world_model_profile("tiny", 1, LAYOUT).config
    if history is not None:
        config = dataclasses.replace(config, dynamics=dataclasses.replace(config.dynamics, history=history))
    run = train(WorldModelModule, config, [tmp / "expert.zarr"], RunConfig(run_dir=tmp / name, max_steps=20, seed=seed, **RUN))
    return str(run.last)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, str]:
    """The planner tests' tiny policy and world model, a second world model of another seed, and a third that reads
    a longer history."""
    tmp = tmp_path_factory.mktemp("ensemble")
    ckpts = train_checkpoints(tmp)
    return {**ckpts, "wm2": _wm(tmp, "wm2", seed=1), "long": _wm(tmp, "long", seed=0, history=3), "tmp": str(tmp)}


def _ensemble(models: dict[str, str], out: Path, *extra: str) -> Path:
    result = gpc("ensemble", models["wm"], models["wm2"], "--out", str(out), *extra)
    assert result.exit_code == 0, result.output
    return out


def _chunks(seed: int, b: int, k: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 100 + 300 * torch.rand(b, k, 16, 2, generator=g)


def test_an_ensemble_scores_every_members_future_and_doubts_their_spread(models, tmp_path):
    ensemble = load_any(_ensemble(models, tmp_path / "e.ckpt", "--pessimism", "0.5"), "pusht")
    assert isinstance(ensemble, WorldModelEnsemble) and ensemble.pessimism == 0.5 and len(ensemble.members) == 2
    one, two = (WorldModelModule.load_from_checkpoint(models[k]) for k in ("wm", "wm2"))
    reward = build_reward(RewardSpec(), PUSHT)
    obs = histories([100000, 100001])
    chunks = _chunks(0, 2, 6)
    scores, futures = ModelScorer(ensemble, reward).objective(obs, PartTimer())(chunks)
    each = [ModelScorer(m, reward).objective(obs, PartTimer())(chunks) for m in (one, two)]
    per_member = torch.stack([s for s, _ in each])
    assert per_member[0].sub(per_member[1]).abs().max() > 1e-3  # the members disagree (else nothing is tested)
    expected = per_member.mean(0) - 0.5 * per_member.std(0, unbiased=False)
    torch.testing.assert_close(scores, expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(futures, (each[0][1] + each[1][1]) / 2, rtol=1e-5, atol=1e-4)  # videos: the mean
    # a per-episode goal reaches every member's reward with its own history's candidates
    goal = torch.tensor([[1.0], [-2.0]])
    by_goal = lambda futures, g: futures[:, -1, 0] * g[:, 0]  # noqa: E731
    history = torch.as_tensor(obs["state"])
    combined, _ = Objective(ensemble, by_goal, history, goal, PartTimer())(chunks)
    own = torch.stack([Objective(m, by_goal, history, goal, PartTimer())(chunks)[0] for m in (one, two)])
    torch.testing.assert_close(combined, own.mean(0) - 0.5 * own.std(0, unbiased=False), rtol=1e-5, atol=1e-4)
    mean = load_any(_ensemble(models, tmp_path / "mean.ckpt"), "pusht")
    torch.testing.assert_close(ModelScorer(mean, reward).objective(obs, PartTimer())(chunks)[0], per_member.mean(0),
                               rtol=1e-5, atol=1e-6)


def test_rank_picks_by_the_combined_score_and_the_ascent_climbs_it(models, tmp_path):
    ensemble = load_any(_ensemble(models, tmp_path / "e.ckpt", "--pessimism", "1"), "pusht")
    policy = PolicyModule.load_from_checkpoint(models["policy"])
    reward = build_reward(RewardSpec(), PUSHT)
    box = dict(action_low=LAYOUT.action.low, action_high=LAYOUT.action.high)
    seeds = [100000, 100001, 100002]
    obs = histories(seeds)
    rank = model_planner(PlannerConfig(kind="rank", num_proposals=8, **box), ensemble, reward, policy)
    plan = rank.plan(obs, gens(seeds))
    assert plan.scores is not None and plan.chosen is not None
    np.testing.assert_array_equal(plan.chosen, plan.scores.argmax(1))
    proposals = rank.proposals(obs, 8, gens(seeds), PartTimer())  # the same generators: the same proposals
    combined, _ = ModelScorer(ensemble, reward).objective(obs, PartTimer())(proposals)
    np.testing.assert_allclose(plan.scores, combined.numpy(), rtol=1e-5, atol=1e-6)
    deployed = load_planner(models["policy"], str(tmp_path / "e.ckpt"), reward, PlannerConfig(kind="rank", num_proposals=8, **box))
    assert isinstance(deployed.world_model, WorldModelEnsemble)  # the README's deployment API takes an ensemble too
    one = {key: value[:1] for key, value in obs.items()}
    np.testing.assert_array_equal(deployed.plan(one, gens(seeds[:1])).chosen, plan.chosen[:1])
    opt = model_planner(PlannerConfig(kind="rank-opt", num_proposals=2, opt_steps=5, keep_best=True, **box),
                        ensemble, reward, policy)
    refined = opt.plan(obs, gens(seeds))
    start, _ = ModelScorer(ensemble, reward).objective(obs, PartTimer())(opt.proposals(obs, 2, gens(seeds), PartTimer()))
    assert refined.scores is not None and (refined.scores.max(1) >= start.numpy().max(1) - 1e-6).all()
    assert (refined.scores.max(1) > start.numpy().max(1) + 1e-4).any()  # the ascent moved the combined score


def test_gpc_eval_plans_with_an_ensemble_and_its_rule_is_part_of_the_run(models, tmp_path):
    mean = _ensemble(models, tmp_path / "e.ckpt")
    common = [models["policy"], "--planner", "rank", "-K", "4", "--seeds", "100000:100002", "--max-steps", "24",
              "--batch", "2", "--workers", "1"]
    out = tmp_path / "run"
    first = gpc("eval", *common, "--world-model", str(mean), "--out", str(out))
    assert first.exit_code == 0, first.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["controller"]["world_model"] == str(mean) and str(mean) in summary["run"]["checkpoints"]
    _ensemble(models, mean, "--pessimism", "1", "--overwrite")  # the same file name, another rule
    again = gpc("eval", *common, "--world-model", str(mean), "--out", str(out), "--resume")
    assert again.exit_code == 2 and "checkpoints" in again.output, again.output  # another run, refused by name
    assert json.loads((out / "summary.json").read_text()) == summary  # and nothing written was touched
    slim = gpc("export", str(mean), "--out", str(tmp_path / "slim.ckpt"))  # nothing of its own to export: one line
    assert slim.exit_code == 2 and "holds no network of its own" in slim.output and not (tmp_path / "slim.ckpt").exists()


@pytest.mark.parametrize("case", ["one member", "a policy", "another history", "negative pessimism", "out is a member"])
def test_bad_members_and_options_get_one_line_and_write_nothing(models, tmp_path, case):
    out = tmp_path / "e.ckpt"
    args = {
        "one member": ([models["wm"]], [], "2..64 members"),
        "a policy": ([models["wm"], models["policy"]], [], "'policy' checkpoint"),
        "another history": ([models["wm"], models["long"]], [], "history 3, not 2"),
        "negative pessimism": ([models["wm"], models["wm2"]], ["--pessimism", "-1"], "--pessimism -1"),
        "out is a member": ([models["wm"], models["wm2"]], [], "is one of the members"),
    }[case]
    members, extra, message = args
    target = Path(models["wm"]) if case == "out is a member" else out
    before = target.read_bytes() if target.exists() else None
    result = gpc("ensemble", *members, "--out", str(target), *extra, "--overwrite")
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output, result.output
    assert len(result.output.strip().splitlines()) == 1
    assert (target.read_bytes() if target.exists() else None) == before


def test_gpc_eval_world_model_judges_the_mean_prediction_where_the_members_held_out_the_same(models, tmp_path):
    ensemble = _ensemble(models, tmp_path / "e.ckpt")
    store = str(Path(models["tmp"]) / "expert.zarr")
    refused = gpc("eval", "world-model", str(ensemble), "--dataset", store, "--out", str(tmp_path / "val"))
    assert refused.exit_code == 2 and "held out different episodes" in refused.output, refused.output  # seeds 0, 1
    result = gpc("eval", "world-model", str(ensemble), "--dataset", store, "--split", "all", "--out", str(tmp_path / "all"))
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "all" / "world_model_eval.json").read_text())
    assert report["ensemble"] == {"members": 2, "pessimism": 0.0}
    one = gpc("eval", "world-model", models["wm"], "--dataset", store, "--split", "all", "--out", str(tmp_path / "one"))
    assert one.exit_code == 0, one.output
    alone = json.loads((tmp_path / "one" / "world_model_eval.json").read_text())
    assert report["windows"] == alone["windows"] and report["mean_over_steps"] != alone["mean_over_steps"]


def test_a_visual_ensemble_scores_every_members_frames_with_the_learned_reward(models, tmp_path):
    from gpc.harness.collection import CollectJob, collect
    from gpc.models.rewards.learned import RewardPredictorModule, reward_profile

    collect(CollectJob(task="pusht", out=tmp_path / "img.zarr", episodes=3, images=True, max_steps=40))
    data, run = [tmp_path / "img.zarr"], dict(RUN, batch_size=8)
    visual = world_model_profile("tiny", 1, LAYOUT, obs="image").config
    members = [str(train(WorldModelModule, visual, data, RunConfig(run_dir=tmp_path / f"w{s}", max_steps=3, seed=s, **run)).last)
               for s in (0, 1)]
    reward_ckpt = train(RewardPredictorModule, reward_profile("tiny", LAYOUT).config, data,
                        RunConfig(run_dir=tmp_path / "r", max_steps=3, **run)).last
    out = tmp_path / "e.ckpt"
    assert gpc("ensemble", *members, "--pessimism", "2", "--out", str(out)).exit_code == 0
    ensemble = load_any(out, "pusht")
    reward = build_reward(RewardSpec(kind="learned", checkpoint=str(reward_ckpt)), PUSHT)
    g = np.random.default_rng(0)
    obs = {"img": g.integers(0, 255, (2, ensemble.n_obs_steps, 96, 96, 3)).astype(np.uint8)}
    chunks = _chunks(1, 2, 3)
    scores, futures = ModelScorer(ensemble, reward).objective(obs, PartTimer())(chunks)
    each = [ModelScorer(m, reward).objective(obs, PartTimer())(chunks) for m in ensemble.members]
    per_member = torch.stack([s for s, _ in each])
    assert futures.shape == each[0][1].shape and futures.dim() == 6 and futures.shape[:2] == (2, 3)  # (B, K, T, 3, S, S)
    torch.testing.assert_close(scores, per_member.mean(0) - 2 * per_member.std(0, unbiased=False), rtol=1e-4, atol=1e-5)
    judged = gpc("eval", "world-model", str(out), "--dataset", str(data[0]), "--split", "all", "--out", str(tmp_path / "j"))
    assert judged.exit_code == 2 and "judge its members one by one" in judged.output
    mixed = gpc("ensemble", members[0], models["wm"], "--out", str(tmp_path / "mixed.ckpt"))
    assert mixed.exit_code == 2 and "observation 'state', not 'img'" in mixed.output and not (tmp_path / "mixed.ckpt").exists()


def test_one_model_twice_plans_as_that_model_even_where_the_ascent_differentiates_a_zero_spread(models, tmp_path):
    out = tmp_path / "twice.ckpt"
    assert gpc("ensemble", models["wm"], models["wm"], "--pessimism", "3", "--out", str(out)).exit_code == 0
    policy = PolicyModule.load_from_checkpoint(models["policy"])
    reward = build_reward(RewardSpec(), PUSHT)
    box = dict(action_low=LAYOUT.action.low, action_high=LAYOUT.action.high)
    config = PlannerConfig(kind="rank-opt", num_proposals=3, opt_steps=4, **box)
    seeds = [100000, 100001]
    obs = histories(seeds)
    twice = model_planner(config, load_any(out), reward, policy).plan(obs, gens(seeds))
    alone = model_planner(config, WorldModelModule.load_from_checkpoint(models["wm"]), reward, policy).plan(obs, gens(seeds))
    assert np.isfinite(twice.chunk).all()  # the spread's gradient at 0 is 0, not NaN
    np.testing.assert_allclose(twice.chunk, alone.chunk, rtol=1e-5, atol=1e-3)
    np.testing.assert_array_equal(twice.chosen, alone.chosen)
