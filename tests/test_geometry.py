import numpy as np
import pytest
import shapely.geometry as sg

from gpc.tasks.pusht import geometry


def _shapely_coverage(block_pose, goal_pose):
    def tee(pose):
        return sg.MultiPolygon([sg.Polygon(b) for b in geometry.tee_vertices(np.asarray(pose))]).buffer(0)

    goal = tee(goal_pose)
    return goal.intersection(tee(block_pose)).area / goal.area


def test_coverage_matches_shapely_on_random_poses():
    rng = np.random.default_rng(0)
    goal = geometry.GOAL_POSE
    poses = np.column_stack([rng.uniform(180, 330, 300), rng.uniform(180, 330, 300), rng.uniform(-np.pi, np.pi, 300)])
    ours = np.array([geometry.coverage(p, goal) for p in poses])
    ref = np.array([_shapely_coverage(p, goal) for p in poses])
    assert np.abs(ours - ref).max() < 1e-9
    assert ours.max() > 0.3  # the sample includes substantial overlaps, not only misses


def test_coverage_and_reward_at_the_goal_and_far_away():
    assert geometry.coverage(geometry.GOAL_POSE) == pytest.approx(1.0, abs=1e-12)
    assert geometry.reward_from_coverage(geometry.coverage(geometry.GOAL_POSE)) == 1.0
    assert geometry.coverage(np.array([50.0, 50.0, 0.0])) == 0.0
    # 0.95 coverage is exactly the success threshold, which scores 1.
    assert geometry.reward_from_coverage(0.95) == 1.0 and geometry.reward_from_coverage(0.475) == pytest.approx(0.5)


def test_registration_error_is_zero_at_goal_and_grows_with_offset():
    g = geometry.GOAL_POSE
    assert geometry.registration_error(g) == pytest.approx(0.0, abs=1e-12)
    shifted = g + np.array([10.0, 0.0, 0.0])
    assert geometry.registration_error(shifted) == pytest.approx(10.0)
    batch = np.stack([g, shifted])
    np.testing.assert_allclose(geometry.registration_error(batch), [0.0, 10.0], atol=1e-12)


def test_keypoints_match_the_recorded_keypoint_field(human_arrays):
    kp = geometry.block_keypoints(human_arrays["state"][:, 2:5])
    err = np.linalg.norm(kp - human_arrays["keypoint"], axis=-1).max(axis=1)
    assert np.mean(err <= 0.05) >= 0.99
