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

    reward = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims)
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
    reward = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims)
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
    final = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims)(poses)
    assert float(final[0]) == pytest.approx(0.0, abs=1e-3)
    disc = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims, RewardConfig(aggregate="discounted", discount=0.5))(poses)
    assert float(disc[0]) == pytest.approx(-(30 + 0.5 * 20 + 0.25 * 10), abs=1e-2)
    with pytest.raises(ValueError, match="aggregate 'best'"):
        RewardConfig(aggregate="best")
    assert isinstance(RegistrationReward(TEE, GOAL, LAYOUT.pose_dims), Reward)


def test_per_candidate_goals_and_batched_shapes():
    reward = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims)
    goals = torch.tensor([[100.0, 100.0, 0.0], [300.0, 300.0, 1.0]])
    x = torch.cat([torch.zeros(2, 3, 2), goals[:, None].expand(2, 3, 3)], dim=-1)
    assert torch.allclose(reward(x, goal=goals), torch.zeros(2), atol=1e-4)
    assert (reward(x) < -10).all()
    d = registration_distance(goals, goals[[1, 0]], TEE)
    assert d.shape == (2,) and torch.allclose(d[0], d[1])
    with pytest.raises(ValueError, match=r"expected \(K, T, D > 4\)"):
        reward(torch.zeros(4, 5))


def _two_objects(goal: tuple[float, ...] | None):
    """A layout of a square that may turn (its goal ignores it) and a disc: the swap task's shape of state."""
    from gpc.datasets.layout import ActionBox, ObjectLayout, StateLayout, TaskLayout

    square = ((-30.0, -30.0), (30.0, -30.0), (30.0, 30.0), (-30.0, 30.0))
    return TaskLayout(name="two", state=StateLayout(dim=7, agent_xy=(0, 1), angle_dims=(4,), action_targets=(0, 1)),
                      action=ActionBox(dim=2, low=0.0, high=512.0),
                      objects=(ObjectLayout("cube", pose=(2, 3), angle=4, vertices=square, goal=None if goal is None else goal[:2]),
                               ObjectLayout("sphere", pose=(5, 6), vertices=((0.0, 0.0),), goal=None if goal is None else goal[2:])))


def test_several_objects_score_the_mean_of_their_registrations():
    layout = _two_objects((100.0, 100.0, 300.0, 300.0))
    reward = RegistrationReward.from_layout(layout)
    assert layout.pose_dims == (2, 3, 5, 6) and layout.primary.frame == (2, 3, 4)
    state = torch.tensor([[[0.0, 0.0, 110.0, 100.0, 0.7, 300.0, 280.0]]], requires_grad=True)
    r = reward(state)
    # the cube is 10 px off (its turn does not count: every corner moves by the same 10 px), the sphere 20 px
    assert r.item() == pytest.approx(-(10.0 + 20.0) / 2, abs=1e-4)
    r.sum().backward()
    grad = state.grad[0, 0]
    assert grad[4] == 0 and grad[2] == pytest.approx(-0.5, abs=1e-4) and grad[6] == pytest.approx(0.5, abs=1e-4)


def test_a_goal_drawn_per_episode_is_passed_with_each_call():
    reward = RegistrationReward.from_layout(_two_objects(None))
    state = torch.tensor([[[0.0, 0.0, 110.0, 100.0, 0.0, 300.0, 280.0]]] * 2)
    with pytest.raises(ValueError, match="pass the episode's goal"):
        reward(state)
    goals = torch.tensor([[110.0, 100.0, 300.0, 280.0], [100.0, 100.0, 300.0, 300.0]])
    assert reward(state, goals).tolist() == pytest.approx([0.0, -15.0], abs=1e-4)


def test_a_layout_refuses_objects_that_share_or_misplace_entries():
    from gpc.datasets.layout import ActionBox, ObjectLayout, StateLayout, TaskLayout

    state, box, point = StateLayout(dim=5, angle_dims=(4,)), ActionBox(dim=2, low=0.0, high=1.0), ((0.0, 0.0),)
    with pytest.raises(ValueError, match="share pose entries"):
        TaskLayout("t", state, box, (ObjectLayout("a", (1, 2), point), ObjectLayout("b", (2, 3), point)))
    with pytest.raises(ValueError, match="not one of angle_dims"):
        TaskLayout("t", state, box, (ObjectLayout("a", (1, 2), point, angle=3),))
    with pytest.raises(ValueError, match="its angle entry must be 4"):
        ObjectLayout("a", (2, 3, 4), point, angle=None)
