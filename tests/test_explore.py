"""Exploration data is contact-rich, reproducible per seed, in bounds and broader than the expert's."""

from __future__ import annotations

import numpy as np
import pytest

from gpc.tasks.pusht import geometry
from gpc.tasks.pusht.env import PushTEnv
from gpc.tasks.pusht.explore import ExploreConfig, ExplorePolicy, evaluate_explore
from gpc.tasks.pusht.geometry import pose_cells


def _rollout(mode: str, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Targets, agent positions they were issued at, and per-step contact flags."""
    env, policy = PushTEnv(), ExplorePolicy(ExploreConfig(mode=mode))
    env.reset(seed=seed)
    policy.reset(seed)
    targets, agents, hits = [], [], []
    for _ in range(steps):
        agents.append(env.sim.state()[:2])
        before = env.sim.snapshot()
        targets.append(policy.act(env.sim, env.goal_pose))
        assert env.sim.snapshot() == before
        hits.append(env.step(targets[-1])[4]["n_contacts"] > 0)
    return np.array(targets), np.array(agents), np.array(hits)


@pytest.mark.parametrize("mode", ["pushes", "perturbed"])
def test_each_mode_is_contact_rich(mode: str) -> None:
    hits = np.concatenate([_rollout(mode, seed, 150)[2] for seed in (100000, 100001)])
    assert hits.mean() >= 0.4


def test_mixed_mode_statistics() -> None:
    res = evaluate_explore(range(100000, 100004), ExploreConfig(), max_steps=200)
    assert res["contact_fraction"] >= 0.4
    assert set(res["modes"]) <= {"perturbed", "pushes"}
    assert res["steps"] == [200] * 4
    assert res["pose_coverage"] > res["expert_pose_coverage"]


def test_mixed_mode_draws_both_kinds() -> None:
    policy = ExplorePolicy()
    modes = set()
    for seed in range(20):
        policy.reset(seed)
        modes.add(policy.episode_mode)
    assert modes == {"perturbed", "pushes"}


@pytest.mark.parametrize("mode", ["pushes", "perturbed"])
def test_same_seed_same_actions(mode: str) -> None:
    a = _rollout(mode, 100002, 80)[0]
    b = _rollout(mode, 100002, 80)[0]
    np.testing.assert_array_equal(a, b)
    c = _rollout(mode, 100003, 80)[0]
    assert not np.allclose(a, c)


@pytest.mark.parametrize("mode", ["pushes", "perturbed"])
def test_actions_in_bounds_and_smooth(mode: str) -> None:
    targets, agents, _ = _rollout(mode, 100004, 200)
    assert np.all((targets >= 0) & (targets <= geometry.WORKSPACE))
    assert np.linalg.norm(np.diff(targets, axis=0), axis=1).max() <= 26.0
    assert np.linalg.norm(targets - agents, axis=1).max() <= 45.0


def test_pose_cells() -> None:
    states = np.array([[0, 0, 10.0, 10.0, 0.1], [0, 0, 12.0, 11.0, 0.2], [0, 0, 500.0, 10.0, 6.2]])
    assert len(pose_cells(states)) == 2


@pytest.mark.parametrize("bad", [dict(mode="random"), dict(perturb_prob=1.5), dict(push_steps=(5, 2)),
                                 dict(wander_speed=(0.0, 3.0)), dict(max_tilt=2.0)])
def test_config_is_validated(bad: dict) -> None:
    with pytest.raises(ValueError):
        ExploreConfig(**bad)
