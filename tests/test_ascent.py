"""Gradient ascent on action chunks (GPC-OPT, RANK+OPT): it raises the predicted reward, its guards and knots
bound where the chunk goes, and the probe replays every iterate in the true simulator."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from tiny_planning import gens, histories, planner
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.models.planning.ascent import AscentTrace, ascend, interpolation, step_size
from gpc.models.planning.objective import Objective, PartTimer


def test_gradient_steps_raise_the_predicted_reward(ckpts):
    p = planner(ckpts, kind="opt", num_proposals=1, opt_steps=10, lr=5.0)
    seeds = (100000, 100001, 100002)
    obs = histories(seeds)
    init = p.policy.sample_batch(obs, 1, gens(seeds))[:, :, p.now :]
    objective = Objective(p.world_model, p.reward, torch.as_tensor(obs["state"]), None, PartTimer())
    before, _ = objective(init)
    after, _ = objective(ascend(objective, init, p.config, PartTimer())[0])
    assert torch.all(after >= before - 1e-4) and torch.any(after > before + 0.1)


def test_ascent_guards_keep_the_chunk_near_its_start_and_never_below_it(ckpts):
    """A trust region bounds every move; keep_best returns the best iterate seen; the trace records each step."""
    seeds = (100000, 100001, 100002)
    obs = histories(seeds)
    p = planner(ckpts, kind="rank-opt", num_proposals=3, opt_steps=6, lr=40.0)  # steps far too large: ascent overshoots
    init = p.policy.sample_batch(obs, 3, gens(seeds))[:, :, p.now :]
    objective = Objective(p.world_model, p.reward, torch.as_tensor(obs["state"]), None, PartTimer())
    start, _ = objective(init)
    box = dataclasses.replace(p.config, trust_region=3.0)
    moved = ascend(objective, init, box, PartTimer())[0]
    assert float((moved - init).abs().max()) <= 3.0 + 1e-4 and float((moved - init).abs().max()) > 2.9
    trace = AscentTrace()
    best = dataclasses.replace(p.config, keep_best=True, lr_decay="cosine")
    chunks, scores, _ = ascend(objective, init, best, PartTimer(), trace)
    assert torch.all(scores >= start - 1e-5)
    np.testing.assert_allclose(scores.numpy(), objective(chunks)[0].detach().numpy(), atol=1e-5)  # the scores are the chunks'
    seen = torch.stack(trace.scores[:-1]).amax(dim=0)  # every iterate scored before each step, and the last
    np.testing.assert_allclose(scores.numpy(), torch.maximum(seen, trace.scores[-1]).numpy(), atol=1e-5)
    assert len(trace.chunks) == len(trace.scores) == 7 and len(trace.action_grads) == len(trace.future_grads) == 6
    assert trace.action_grads[0].shape == (3, 3, init.shape[2]) and trace.future_grads[0].shape[:2] == (3, 3)
    assert float(trace.action_grads[0].sum()) > 0 and float(trace.future_grads[0].sum()) > 0
    assert step_size(best, 0) == 40.0 and step_size(best, 3) == pytest.approx(20.0) and step_size(best, 6) == pytest.approx(0.0)
    weights = list(p.world_model.parameters())  # the planner froze them: ascent computed no gradient for the model
    assert weights and all(not w.requires_grad and w.grad is None for w in weights)


def test_knotted_ascent_bends_the_proposal_smoothly_and_one_knot_per_action_is_plain_ascent(ckpts):
    """With n knots the chunk moves by a piecewise-linear offset through n points (bounded by the trust region);
    with a knot per action it is the plain ascent."""
    weights = interpolation(16, 4)
    np.testing.assert_allclose(weights.sum(dim=1).numpy(), 1.0, atol=1e-6)
    assert torch.equal(interpolation(16, 16), torch.eye(16)) and torch.equal(interpolation(5, 1), torch.ones(5, 1))
    seeds = (100000, 100001, 100002)
    obs = histories(seeds)
    p = planner(ckpts, kind="rank-opt", num_proposals=2, opt_steps=8, lr=5.0)
    init = p.policy.sample_batch(obs, 2, gens(seeds))[:, :, p.now :]
    objective = Objective(p.world_model, p.reward, torch.as_tensor(obs["state"]), None, PartTimer())
    before, _ = objective(init)
    trace = AscentTrace()
    knotted = dataclasses.replace(p.config, knots=3)
    chunks, scores, _ = ascend(objective, init, knotted, PartTimer(), trace)
    offsets = chunks - init
    basis = interpolation(init.shape[2], 3)
    through_knots = basis @ (torch.linalg.pinv(basis) @ offsets)  # the offset is a blend of 3 knots
    np.testing.assert_allclose(through_knots.numpy(), offsets.numpy(), atol=1e-4)
    assert float(offsets.abs().max()) > 1.0 and torch.any(scores > before + 0.1)
    np.testing.assert_allclose(scores.numpy(), objective(chunks)[0].detach().numpy(), atol=1e-5)
    assert len(trace.chunks) == 9 and float(trace.action_grads[0].sum()) > 0
    bounded = ascend(objective, init, dataclasses.replace(knotted, trust_region=2.0), PartTimer())[0]
    assert float((bounded - init).abs().max()) <= 2.0 + 1e-4
    for lr in (5.0, 200.0):  # 200 px steps: the action box binds, and a knot per action still is the plain ascent
        plain = ascend(objective, init, dataclasses.replace(p.config, lr=lr), PartTimer())[0]
        per_action = ascend(objective, init, dataclasses.replace(p.config, lr=lr, knots=init.shape[2]), PartTimer())[0]
        np.testing.assert_allclose(per_action.numpy(), plain.numpy(), atol=1e-3)
    wide = ascend(objective, init, dataclasses.replace(knotted, lr=200.0), PartTimer())[0]
    low, high = p.config.action_low, p.config.action_high
    assert float(wide.min()) >= low and float(wide.max()) <= high and bool(((wide == low) | (wide == high)).any())


def test_the_ascent_probe_scores_every_iterate_in_the_true_simulator(ckpts, tmp_path):
    args = ["eval", "ascent", ckpts["policy"], "--world-model", ckpts["wm"], "--seeds", "200000:200002", "--max-steps", "16",
            "--batch", "2"]
    res = CliRunner().invoke(app, [*args, "--planner", "rank-opt", "-K", "3", "-M", "4", "--out", str(tmp_path / "a.md")])
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "a.json").read_text())
    assert report["decisions"] == 2 * 2 and report["candidates"] == 4 * 3 and report["steps"] == 4  # 2 episodes x 16 steps, 8 per decision
    step = report["per_step"]
    assert len(step["predicted_gain_mean"]) == 5 and step["predicted_gain_mean"][0] == 0.0 and step["moved_mean"][0] == 0.0
    assert 0.0 <= report["final"]["share_fooled"] <= report["final"]["share_predicted_up"] <= 1.0
    assert report["model_error"]["start_mean"] > 0 and len(report["gradient"]["per_action_first_step"]) == 15
    assert report["reward_on_true_frames"] is None  # state futures: the reward already reads true states
    pick = report["selection"]  # K = 3: what ranking and ascent each deliver over the average proposal
    assert pick["rank_gain_mean"] <= pick["best_proposal_gain_mean"] and pick["best_proposal_gain_mean"] >= 0.0
    assert "| share fooled" in (tmp_path / "a.md").read_text()
    res = CliRunner().invoke(app, [*args, "--planner", "rank", "--out", str(tmp_path / "b.md")])
    assert res.exit_code != 0 and "takes no gradient steps" in res.output and not (tmp_path / "b.md").exists()
