"""Block Stacking on MuJoCo: the environment, exact save/restore, contacts, reward geometry, rendering and collectors."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import gpc.tasks.stack  # noqa: F401  (registers gpc/Stack-v0)
from gpc.tasks.stack import geometry
from gpc.tasks.stack.env import MAX_YAW, MIN_APART, START_RANGE, StackEnv, initial_scene
from gpc.tasks.stack.expert import StackExpert
from gpc.tasks.stack.explore import ExplorePolicy, evaluate_explore
from gpc.tasks.stack.record import RecordConfig, episode_scores, record_episode
from gpc.tasks.stack.render import camera, draw_state
from gpc.tasks.stack.scene import CAMERA_FOVY, CUBE_SIDE, StackSim


def _steps(env: StackEnv, policy, n: int) -> list[dict]:
    return [env.step(policy.act(env.sim))[4] for _ in range(n)]


def test_gym_env_observations_and_bad_input() -> None:
    env = gym.make("gpc/Stack-v0", obs_type="state+pixels")
    obs, _ = env.reset(seed=100000)
    assert obs["state"].shape == (18,) and obs["pixels"].shape == (96, 96, 3) and obs["pixels"].dtype == np.uint8
    assert env.observation_space.contains(obs) and env.spec is not None and env.spec.max_episode_steps == 300
    np.testing.assert_allclose(obs["state"], initial_scene(100000), atol=1e-12)  # the reset lands on the drawn state
    with pytest.raises(ValueError, match="obs_type"):
        StackEnv(obs_type="keypoints")
    for bad in (np.zeros(3), np.array([0.0, 0.0, 0.1, np.nan])):
        with pytest.raises(ValueError, match="action must be 4 finite numbers"):
            StackEnv().step(bad)
    with pytest.raises(ValueError, match="112 numbers"):
        StackSim().restore(np.zeros(16))  # another model's state


def test_seeds_draw_flat_apart_cubes_and_repeat() -> None:
    for seed in range(100000, 100100):
        s = initial_scene(seed)
        red, blue = s[geometry.RED], s[geometry.BLUE]
        assert np.linalg.norm(red[:2] - blue[:2]) >= MIN_APART and np.all(np.abs(np.r_[red[:2], blue[:2]]) <= START_RANGE)
        assert red[2] == blue[2] == CUBE_SIDE / 2 and geometry.reward(s) < 0.1
        for quat in (s[geometry.RED_QUAT], s[geometry.BLUE_QUAT]):
            assert quat[1] == quat[2] == 0 and abs(2 * np.arcsin(quat[3])) <= MAX_YAW + 1e-12
    np.testing.assert_array_equal(initial_scene(7), initial_scene(7))


def test_determinism_and_exact_restore() -> None:
    env = StackEnv()
    env.reset(seed=3)
    policy = ExplorePolicy()
    policy.reset(3)
    _steps(env, policy, 25)
    saved = env.sim.vector()
    rng = np.random.default_rng(0)
    actions = [env.sim.state()[:4] + rng.normal(0, 0.02, 4) for _ in range(15)]
    first = [env.step(a)[4]["state"] for a in actions]
    other = StackSim()  # a fresh model restored from the vector replays bit for bit
    other.restore(saved)
    for a, expected in zip(actions, first):
        other.step(a)
        np.testing.assert_array_equal(other.state(), expected)
    env.reset(seed=3)  # and so does a second run from the same seed
    policy.reset(3)
    _steps(env, policy, 25)
    np.testing.assert_array_equal(env.sim.vector(), saved)


def test_reset_to_state_lands_exactly() -> None:
    s = initial_scene(11)
    s[:4] = [0.05, -0.02, 0.09, 0.03]
    s[geometry.RED] = s[geometry.BLUE] + [0.0, 0.0, CUBE_SIDE]
    obs, _ = StackEnv().reset(seed=0, options={"reset_to_state": s})
    np.testing.assert_allclose(obs, s, atol=1e-15)


def test_contacts_are_counted_per_pair() -> None:
    env = StackEnv()
    env.reset(seed=100001)
    expert = StackExpert()
    expert.reset(100001)
    infos = _steps(env, expert, 60)
    pairs = np.array([i["contacts"] > 0 for i in infos])
    assert not pairs[0].any()  # the gripper starts in the air
    closed = [i for i, phase_info in enumerate(infos) if phase_info["contacts"][0] > 0]
    assert closed and pairs[closed[0]:, 0].sum() >= 5  # it holds the red cube for a while
    assert pairs[:, 2].any() and not pairs[:, 1].any()  # the red cube touches the blue one; the gripper never does
    assert all(i["n_contacts"] == int(p.sum()) for i, p in zip(infos, pairs))


def test_reward_geometry() -> None:
    s = initial_scene(5)
    s[geometry.RED] = s[geometry.BLUE] + [0.0, 0.0, CUBE_SIDE]
    assert geometry.reward(s) == 1.0 and geometry.stacked(s)
    for offset, expected in (([0.01, 0, 0], 0.9), ([0, 0.03, 0.04], 0.5), ([0.2, 0, 0], 0.0)):
        moved = s.copy()
        moved[geometry.RED] += offset
        assert geometry.reward(moved) == pytest.approx(expected)
    s[:4] = [*s[geometry.RED][:2], s[geometry.RED][2] + 0.05, 0.08]  # open, fingertips 1.5 cm above the top
    assert geometry.released(s)
    s[3] = 0.04
    assert not geometry.released(s)  # closed
    s[3], s[2] = 0.08, s[geometry.RED][2]
    assert not geometry.released(s)  # open but around the cube
    batch = np.stack([s, initial_scene(1)])
    assert geometry.reward(batch).shape == (2,)


def test_unstable_simulation_truncates_with_zero_reward(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the divergence to ./MUJOCO_LOG.TXT
    env = StackEnv()
    env.reset(seed=2)
    vector = env.sim.vector()
    vector[1 + env.sim.model.nq] = np.nan  # a velocity: the state of a diverged run
    env.sim.restore(vector)
    _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, 0.1, 0.05]))
    assert truncated and not terminated and reward == 0.0 and "diverged" in info["unstable"]
    # a served robot (`gpc serve`'s simulator client) ends that episode as `gpc eval` does, and says why
    from types import SimpleNamespace

    from gpc.serving.robot import SimRobot

    robot = SimRobot(SimpleNamespace(metadata={"task": "stack", "observations": ["state"], "goal": "fixed"}))  # type: ignore[arg-type]
    robot.reset(seed=2)
    robot.env.sim.restore(vector)
    assert robot.step(np.array([0.0, 0.0, 0.1, 0.05])) and "diverged" in robot.row["unstable"] and robot.row["steps"] == 1
    assert "distance_max" not in robot.row and robot.row["distance_min"] >= 0  # the closest the red cube came
    sim = StackSim()
    s = initial_scene(2)
    s[geometry.RED] = s[geometry.BLUE] + [0.005, 0.0, 0.0]  # the cubes inside each other
    sim.set_state(s)
    assert "interpenetrate" in sim.unstable()


def test_expert_stacks_and_records() -> None:
    for seed in (100000, 100050):
        data, stats = record_episode(StackExpert(), seed, RecordConfig(images=True))
        assert stats.success and stats.score > 0.99 and stats.steps < 80
        assert data["state"].shape == (stats.steps, 18) and data["action"].shape == (stats.steps, 4)
        assert data["img"].shape == (stats.steps, 96, 96, 3) and data["n_contacts"].shape == (stats.steps, 1)
        final = data["state"][-1]
        assert geometry.distance(final) < geometry.ON_TARGET and geometry.released(final)
        # the stored states score as the episode did (the last stored state precedes the last step)
        assert episode_scores(data["state"], np.array([stats.steps]))[0] == pytest.approx(stats.score, abs=2e-3)
    a = record_episode(StackExpert(), 100000, RecordConfig(images=False))[0]["action"]
    b = record_episode(StackExpert(), 100001, RecordConfig(images=False))[0]["action"]
    assert not np.array_equal(a[:5], b[:5])  # seeded style and noise


def test_explorer_touches_and_knocks_over() -> None:
    result = evaluate_explore(range(2), max_steps=150)
    assert result["steps"] == 300 and result["contact_fraction"] >= 0.3
    assert min(result["gripper_red"], result["gripper_blue"], result["red_blue"]) > 0.1  # every pair touches, often
    assert result["knocked_over"] >= 0.5  # episodes with a cube tipped past 30 degrees


def test_quaternions_are_continuous_through_tumbles() -> None:
    """A cube's quaternion moves smoothly while it turns over (no sign flip as qw crosses 0) and is a unit one."""
    data, _ = record_episode(ExplorePolicy(), 5, RecordConfig(images=False))
    quats = data["state"][:, np.r_[geometry.RED_QUAT, geometry.BLUE_QUAT]].reshape(-1, 2, 4)
    assert (quats[..., 0] < 0).any() and (quats[..., 0] > 0).any()  # turned past qw = 0 and back
    # a sign flip where qw crosses 0 moves some entry by at least 2 / sqrt(3); a fast tumble by about 0.6
    assert np.abs(np.diff(quats, axis=0)).max() < 1.0
    np.testing.assert_allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-5)


def test_own_renderer_draws_cubes_where_they_are() -> None:
    s = initial_scene(4)
    frame = draw_state(s, 96)
    assert frame.shape == (96, 96, 3) and frame.dtype == np.uint8
    red = (frame[..., 0] > 150) & (frame[..., 1] < 90)
    blue = (frame[..., 2] > 150) & (frame[..., 0] < 90)
    assert 10 < red.sum() < 200 and 10 < blue.sum() < 200
    pos, rot = camera()
    focal = 48 / np.tan(np.radians(CAMERA_FOVY) / 2)
    for mask, centre in ((red, s[geometry.RED]), (blue, s[geometry.BLUE])):
        x, y, z = rot @ (centre - pos)  # right, up, forward
        at = np.array([48 - focal * y / z, 48 + focal * x / z]) - 0.5  # the cube's centre through the pinhole (row, col)
        assert np.linalg.norm(np.argwhere(mask).mean(axis=0) - at) < 2.0, (at, np.argwhere(mask).mean(axis=0))
    lifted = s.copy()
    lifted[6] += 0.05
    red_up = (draw_state(lifted, 96)[..., 0] > 150) & (draw_state(lifted, 96)[..., 1] < 90)
    assert np.argwhere(red_up)[:, 0].mean() < np.argwhere(red)[:, 0].mean() - 3  # a lifted cube rises in the frame


_MUJOCO_RENDER = """
import json, sys
import numpy as np
import mujoco
from gpc.tasks.stack.env import initial_scene
from gpc.tasks.stack.render import draw_state
from gpc.tasks.stack.scene import StackSim
sim = StackSim()
try:  # only MuJoCo's own renderer may be missing here (no EGL or OSMesa); gpc's code must load
    renderer = mujoco.Renderer(sim.model, 96, 96)
except Exception as exc:
    print(json.dumps({"skip": f"{type(exc).__name__}: {exc}"}))
    sys.exit(0)
out = []
for seed in range(4):
    s = initial_scene(seed)
    s[:3] = [s[4], s[5], 0.02 + 0.03 * seed]
    s[6] += 0.03 * seed
    s[3] = 0.045 + 0.01 * seed
    sim.set_state(s)
    renderer.update_scene(sim.data, camera="fixed")
    theirs, ours = renderer.render().astype(int), draw_state(sim.state(), 96).astype(int)
    masks = [((im[..., 0] > 150) & (im[..., 1] < 90), (im[..., 2] > 150) & (im[..., 0] < 90)) for im in (theirs, ours)]
    iou = [float((a & b).sum() / max((a | b).sum(), 1)) for a, b in zip(*masks)]
    shift = [float(np.linalg.norm(np.argwhere(a).mean(0) - np.argwhere(b).mean(0))) for a, b in zip(*masks)]
    out.append({"mad": float(np.abs(theirs - ours).mean()), "iou": iou, "centroid_px": shift})
print(json.dumps({"frames": out}))
"""


def test_own_renderer_matches_mujoco_where_opengl_exists() -> None:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    run = subprocess.run([sys.executable, "-c", _MUJOCO_RENDER], capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    if "skip" in result:
        pytest.skip(f"MuJoCo cannot render here (no OpenGL: {result['skip']})")
    for frame in result["frames"]:
        # mean absolute difference of 0.1-0.4 of 255 measured; cubes of ~20 px agree to a fraction of a pixel
        assert frame["mad"] < 1.5 and min(frame["iou"]) > 0.7 and max(frame["centroid_px"]) < 0.5, frame


def test_planning_reward_is_the_env_reward_before_clipping_and_differentiable() -> None:
    import torch

    from gpc.models.rewards.state import state_reward
    from gpc.tasks import get_task
    from gpc.tasks.stack.reward import StackReward

    task = get_task("stack")
    loaded = state_reward(task.state_reward, task.layout)  # named by module: imported and registered on first use
    assert isinstance(loaded, StackReward)
    states = np.stack([initial_scene(seed) for seed in range(6)])
    states[3, geometry.RED] = states[3, geometry.BLUE] + [0.004, 0.0, CUBE_SIDE]
    futures = torch.tensor(states, dtype=torch.float64)[:, None].repeat(1, 3, 1).requires_grad_(True)
    scores = StackReward(release=0.0)(futures)
    np.testing.assert_allclose(np.clip(1 + scores.detach().numpy(), 0, 1), geometry.reward(states), atol=1e-3)
    # unclipped: minus the distance in units of 10 cm, far beyond the environment's zero (the starts lie 10 cm apart)
    unclipped = scores.detach().numpy()
    np.testing.assert_allclose(unclipped, -geometry.distance(states) / geometry.REWARD_DISTANCE, atol=2e-3)
    assert unclipped[3] == pytest.approx(-0.04, abs=2e-3) and (np.delete(unclipped, 3) < -1.0).all()
    loaded(futures).sum().backward()
    assert futures.grad is not None and torch.isfinite(futures.grad).all() and futures.grad[:, -1].abs().sum() > 0


def test_planning_reward_pays_for_letting_go_on_the_target_only() -> None:
    import torch

    from gpc.tasks.stack.reward import NEAR, StackReward

    on = initial_scene(3)
    on[geometry.RED] = on[geometry.BLUE] + [0.003, 0.0, CUBE_SIDE]
    held, let_go, far = on.copy(), on.copy(), on.copy()
    held[0:4] = [*on[geometry.RED], 0.04]  # fingers closed on the cube
    let_go[0:4] = [*(on[geometry.RED] + [0, 0, 0.06]), 0.08]  # open, fingertips 2.5 cm above its top
    far[geometry.RED] += [0.05, 0.0, 0.0]
    far[0:4] = [*(far[geometry.RED] + [0, 0, 0.06]), 0.08]
    states = np.stack([held, let_go, far])
    assert list(geometry.released(states)) == [False, True, True]
    x = torch.tensor(states)[:, None]
    bonus = (StackReward(release=0.5).per_step(x) - StackReward(release=0.0).per_step(x))[:, 0].numpy()
    d = geometry.distance(states)
    assert bonus[0] < 1e-3 and bonus[2] < 1e-4  # held on target, or let go 5 cm off it: nothing
    assert bonus[1] == pytest.approx(0.5 * np.exp(-(d[1] / NEAR) ** 2), rel=0.1)
    rng = np.random.default_rng(0)  # the soft release agrees with the environment's on states around a stack
    many = np.repeat(on[None], 400, axis=0)
    many[:, 0:3] = on[geometry.RED] + rng.uniform([-0.1, -0.1, -0.03], [0.1, 0.1, 0.08], (400, 3))
    many[:, 3] = rng.uniform(0.0, 0.09, 400)
    soft = StackReward.let_go(torch.tensor(many)).numpy()
    assert np.mean((soft > 0.5) == geometry.released(many)) > 0.95


def test_ground_truth_world_model_replays_the_env_exactly() -> None:
    from gpc.tasks import get_task

    task = get_task("stack")
    env = task.make_env("fixed")
    env.reset(seed=9)
    obs = task.observe(env, False, True)
    actions = np.array([[0.02 * t, -0.01 * t, 0.1 - 0.005 * t, 0.06] for t in range(6)])
    predicted = task.simulator().rollout(obs[task.sim_key][None, None], actions[None]).numpy()[0]
    truth = [env.step(a)[4]["state"] for a in actions]
    np.testing.assert_allclose(predicted, np.array(truth, dtype=np.float32), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"\(K, T, 4\)"):
        task.simulator().rollout(obs[task.sim_key][None, None], np.zeros((1, 6, 2)))
