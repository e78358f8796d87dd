"""The registration reward: 0 at the goal, minus the mean vertex distance elsewhere, finite gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gpc.models.rewards.registration import RegistrationReward, Reward, RewardConfig, registration_distance
from gpc.tasks.pusht import LAYOUT

TEE = torch.tensor([[-60, 30], [60, 30], [60, 0], [-60, 0], [-15, 30], [-15, 120], [15, 120], [15, 30]], dtype=torch.float32)
GOAL = torch.tensor([256.0, 256.0, math.pi / 4])


def states(poses: list[list[float]], agent=(100.0, 100.0)) -> torch.Tensor:
    """``(K, 1, 5)`` Push-T states from block poses."""
    return torch.tensor([[[*agent, *p]] for p in poses], dtype=torch.float32)


def test_zero_at_goal_negative_elsewhere_and_equal_to_the_task_geometry():
    from gpc.tasks.pusht.geometry import GOAL_POSE, registration_error

    reward = RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose)
    poses = [[256.0, 256.0, math.pi / 4], [256.0, 256.0, math.pi / 4 + 2 * math.pi], [266.0, 256.0, math.pi / 4],
             [100.0, 400.0, 2.0], [256.0, 256.0, math.pi / 4 + math.pi]]
    r = reward(states(poses))
    assert r.shape == (5,)
    assert abs(float(r[0])) < 1e-4 and abs(float(r[1])) < 1e-3  # a full turn is the same pose
    assert float(r[2]) == pytest.approx(-10.0, abs=1e-3)  # a pure 10 px shift moves every vertex 10 px
    expected = -registration_error(np.array(poses), GOAL_POSE)
    assert np.allclose(r.numpy(), expected, atol=1e-2)
    assert (r[2:] < -1.0).all()


def test_gradient_is_finite_at_the_goal_and_points_towards_it():
    reward = RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose)
    x = states([[256.0, 256.0, math.pi / 4], [300.0, 240.0, 1.0]]).requires_grad_(True)
    reward(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert torch.allclose(x.grad[0], torch.zeros(5), atol=1e-4)
    g = x.grad[1, 0]
    assert g[2] < 0 and g[3] > 0 and g[4] < 0  # towards x 256, y 256 and angle pi/4
    assert 0.5 < float(g[2:4].norm()) <= 1.0 + 1e-5  # a mean of unit vectors
    assert torch.equal(x.grad[:, :, :2], torch.zeros(2, 1, 2))  # the agent does not enter the reward


def test_final_step_by_default_or_a_discounted_sum():
    poses = torch.tensor([[[0, 0, 256, 256 + 10 * t, math.pi / 4] for t in (3, 2, 1, 0)]], dtype=torch.float32)
    final = RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose)(poses)
    assert float(final[0]) == pytest.approx(0.0, abs=1e-3)
    disc = RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose, RewardConfig(aggregate="discounted", discount=0.5))(poses)
    assert float(disc[0]) == pytest.approx(-(30 + 0.5 * 20 + 0.25 * 10), abs=1e-2)
    with pytest.raises(ValueError, match="aggregate 'best'"):
        RewardConfig(aggregate="best")
    assert isinstance(RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose), Reward)


def test_per_candidate_goals_and_batched_shapes():
    reward = RegistrationReward(TEE, GOAL, LAYOUT.state.object_pose)
    goals = torch.tensor([[100.0, 100.0, 0.0], [300.0, 300.0, 1.0]])
    x = torch.cat([torch.zeros(2, 3, 2), goals[:, None].expand(2, 3, 3)], dim=-1)
    assert torch.allclose(reward(x, goal=goals), torch.zeros(2), atol=1e-4)
    assert (reward(x) < -10).all()
    d = registration_distance(goals, goals[[1, 0]], TEE)
    assert d.shape == (2,) and torch.allclose(d[0], d[1])
    with pytest.raises(ValueError, match=r"expected \(K, T, D > 4\)"):
        reward(torch.zeros(4, 5))
