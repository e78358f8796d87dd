"""The state world model's evaluation on held-out windows: errors against "nothing moves", and the task's reward."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_world_model import phase1, phase2, runs, store  # noqa: F401  (the trained models, module fixtures)

from gpc.models.rewards.registration import RewardConfig
from gpc.models.rewards.state import state_reward
from gpc.models.stats import spearman
from gpc.models.world_models.eval_state import evaluate_rollouts, markdown_table
from gpc.tasks.pusht import LAYOUT


def test_eval_beats_the_nothing_moves_baseline(phase2, store):  # noqa: F811  (the fixtures imported above)
    report = evaluate_rollouts(phase2.module, [store], layout=LAYOUT)
    first, last = report["steps"][0], report["steps"][-1]
    assert report["split"] == "val" and report["episodes"] == 2 and len(report["steps"]) == 8
    assert first["model"]["agent_px"] < 0.6 * first["baseline"]["agent_px"]  # about 4 px against 9
    assert last["model"]["registration_px"] < last["baseline"]["registration_px"]
    assert report["mean_over_steps"]["model"]["object_px"] < report["mean_over_steps"]["baseline"]["object_px"]


def test_eval_judges_the_task_reward(phase2, store):  # noqa: F811
    reward = state_reward("registration", LAYOUT, RewardConfig(aggregate="final"))
    report = evaluate_rollouts(phase2.module, [store], layout=LAYOUT, reward=reward)
    for row in report["steps"]:  # |r(pred) - r(true)| <= the vertices' distance between them (triangle inequality)
        for guess in ("model", "baseline"):
            assert row[guess]["reward"] <= row[guess]["registration_px"] + 1e-3, row
    assert report["steps"][-1]["model"]["reward"] < report["steps"][-1]["baseline"]["reward"]
    change = report["reward_change"]  # "nothing moves" predicts no change: only the model's ranking is scored
    assert change["spearman"] > 0.5 and change["recorded_std"] > 0, change
    assert "Spearman" in markdown_table(report) and "reward" in markdown_table(report)
    assert spearman(np.array([1.0, 2.0, 3.0]), np.array([3.0, 5.0, 9.0])) == pytest.approx(1.0)
    assert math.isnan(spearman(np.array([1.0, 2.0, 3.0]), np.array([2.0, 2.0, 2.0])))
