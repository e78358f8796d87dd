"""Triangle Drawing: the canvas, its observation, reward geometry (against shapely), save/restore, rendering, the
expert, exploration and recording."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import shapely
import shapely.geometry as sg

import gpc.tasks.draw  # noqa: F401  (registers gpc/Draw-v0)
from gpc.tasks.draw import geometry
from gpc.tasks.draw.env import DrawEnv, initial_scene
from gpc.tasks.draw.expert import DrawExpert
from gpc.tasks.draw.explore import ExploreConfig, ExplorePolicy, evaluate_explore
from gpc.tasks.draw.record import RecordConfig, episode_scores, record_episode
from gpc.tasks.draw.render import INK, TARGET, draw_state
from gpc.tasks.draw.sim import SIM_DIM, DrawSim
from gpc.tasks.draw.sim_model import SimulatorModel
from gpc.tasks.planar.draw import AGENT_EDGE


def _cells_within(shape: sg.base.BaseGeometry) -> np.ndarray:
    """The grid's cells whose centre lies in ``shape`` (shapely's own test, independent of ours)."""
    x, y = geometry.cell_points().transpose(2, 0, 1)
    return shapely.contains_xy(shape, x, y) | shapely.intersects_xy(shape.boundary, x, y)


def test_gym_env_observations_and_bad_actions() -> None:
    env = gym.make("gpc/Draw-v0", obs_type="state+pixels")
    obs, info = env.reset(seed=100000)
    assert obs["state"].shape == (33,) and obs["pixels"].shape == (96, 96, 3) and env.observation_space.contains(obs)
    vertices, start = initial_scene(100000)
    np.testing.assert_array_equal(obs["state"][:2], vertices[start])  # the pen starts down on the seed's vertex
    np.testing.assert_array_equal(obs["state"][2:8], vertices.ravel())
    assert 0.0 < info["f1"] < 0.1 and info["off_outline"] == 0.0  # its first dot lies on the outline
    assert env.spec is not None and env.spec.max_episode_steps == 300
    with pytest.raises(ValueError, match="obs_type"):
        DrawEnv(obs_type="keypoints")
    with pytest.raises(ValueError, match="action"):
        DrawEnv().step(np.array([np.nan, 1.0]))
    a, b = DrawEnv(), DrawEnv()
    a.reset(seed=5)
    b.reset(seed=5)
    a.step(np.array([-300.0, 900.0]))  # out of the box: clipped as the action box says
    b.step(np.array([0.0, 512.0]))
    np.testing.assert_array_equal(a.sim.vector(), b.sim.vector())


def test_seeds_draw_varied_triangles_that_fit() -> None:
    starts = set()
    for seed in range(100000, 100100):
        vertices, start = initial_scene(seed)
        starts.add(start)
        assert vertices.min() >= geometry.MARGIN and vertices.max() <= 512 - geometry.MARGIN
        assert geometry.edge_lengths(vertices).min() >= geometry.MIN_EDGE
        assert geometry.corner_angles(vertices).sum() == pytest.approx(np.pi)
    assert starts == {0, 1, 2} and not np.allclose(initial_scene(1)[0], initial_scene(2)[0])


def test_band_bins_and_f1_match_an_independent_raster() -> None:
    """The band is the outline buffered by the pen's radius (shapely), the ink the pen's path buffered alike; the
    F1 the scene reports, and the one its state's summary implies, are shapely's cell counts'."""
    vertices = initial_scene(100007)[0]
    outline = sg.LinearRing(vertices).buffer(geometry.PEN_RADIUS, quad_segs=64)
    band = geometry.Band.of(vertices)
    reference = _cells_within(outline)
    assert np.count_nonzero((band.bins >= 0) != reference) <= 2  # cells on the band's very edge may round either way
    assert band.size == int((band.bins >= 0).sum()) and band.bin_sizes.min() > 0.5 * band.bin_sizes.mean()
    sim = DrawSim(vertices)
    sim.place_pen(vertices[0])
    paths = [sim.step(t) for t in ([300.0, 300.0], [310.0, 120.0], vertices[1], vertices[1], [100.0, 400.0])]
    stroke = sg.LineString(np.concatenate(paths)).buffer(geometry.PEN_RADIUS, quad_segs=64)
    ink = _cells_within(stroke)
    assert np.count_nonzero(ink != sim.ink) <= 2
    on, off = np.count_nonzero(ink & reference), np.count_nonzero(ink & ~reference)
    f1 = 2 * on / (on + off + np.count_nonzero(reference))
    assert sim.f1() == pytest.approx(f1, abs=0.01) and 0.1 < f1 < 0.8
    assert geometry.f1_from_summary(sim.state()[8:]) == pytest.approx(sim.f1(), abs=1e-12)
    # tracing the outline exactly inks exactly the band: F1 1; the stroke moved aside by d loses about d / 20 of each edge
    edges = np.roll(vertices, -1, axis=0) - vertices
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / geometry.edge_lengths(vertices)[:, None]
    for shift in (np.zeros(2), np.array([6.0, 0.0])):
        sim = DrawSim(vertices)
        sim.ink[:] = _cells_within(sg.LinearRing(vertices + shift).buffer(geometry.PEN_RADIUS, quad_segs=64))
        sim.set_triangle(vertices)
        lost = np.abs(normals @ shift) / (2 * geometry.PEN_RADIUS)
        expected = (geometry.edge_lengths(vertices) * (1 - lost)).sum() / geometry.edge_lengths(vertices).sum()
        assert sim.f1() == pytest.approx(expected, abs=0.03)
    assert geometry.is_success(0.91) and not geometry.is_success(0.9)


def test_save_and_restore_are_exact_and_the_ceiling_replays_the_canvas() -> None:
    env = DrawEnv()
    env.reset(seed=100002)
    policy = ExplorePolicy(ExploreConfig(mode="scribbles"))
    policy.reset(3)
    for _ in range(25):
        env.step(policy.act(env.sim))
    saved = env.sim.vector()
    assert saved.shape == (SIM_DIM,) and env.sim.ink.any()
    actions = [policy.act(env.sim) for _ in range(12)]
    true = [env.step(a)[0] for a in actions]
    other = DrawEnv()
    obs, _ = other.reset(seed=9, options={"reset_to_state": saved})  # another seed's triangle: the vector's wins
    np.testing.assert_array_equal(other.sim.vector(), saved)
    np.testing.assert_array_equal(np.array([other.step(a)[0] for a in actions]), np.array(true))
    np.testing.assert_array_equal(other.sim.ink, env.sim.ink)
    predicted = SimulatorModel().rollout(saved[None, None], np.array(actions)[None])
    np.testing.assert_allclose(predicted[0].numpy(), np.array(true), rtol=1e-6, atol=1e-4)
    with pytest.raises(ValueError, match="reset_to_state"):
        other.reset(options={"reset_to_state": true[0]})  # a state's summary cannot say where the ink lies


def test_render_draws_target_ink_and_pen() -> None:
    env = DrawEnv()
    env.reset(seed=100001)
    vertices = env.sim.vertices
    start = env.sim.pen()
    for target in (vertices[(env.start_vertex + 1) % 3],) * 8:
        env.step(target)
    frame = env.frame(512)

    def at(xy) -> tuple[int, ...]:
        return tuple(int(v) for v in frame[int(round(xy[1])), int(round(xy[0]))])

    middle = (start + vertices[(env.start_vertex + 1) % 3]) / 2
    undrawn = (vertices[(env.start_vertex + 1) % 3] + vertices[(env.start_vertex + 2) % 3]) / 2
    assert at(middle) == INK and at(undrawn) == TARGET and at(vertices.mean(axis=0)) == (255, 255, 255)
    assert at(env.sim.pen() + [geometry.PEN_RADIUS + 1.5, 0.0]) == AGENT_EDGE
    np.testing.assert_array_equal(env.render(), env.frame(96))
    drawn = draw_state(env.sim.state(), None, 512)  # the summary's view: the inked bins dark, the rest faint
    assert tuple(int(v) for v in drawn[int(middle[1]), int(middle[0])]) == INK
    assert tuple(int(v) for v in drawn[int(undrawn[1]), int(undrawn[0])]) == TARGET


def test_expert_draws_the_triangle_either_way_and_is_repeatable() -> None:
    firsts = []
    for seed in range(100000, 100006):
        data, stats = record_episode(DrawExpert(), seed, RecordConfig(images=False))
        assert stats.success and stats.score > 0.9 and stats.steps < 120
        firsts.append(data["action"][5] - data["state"][0, :2])
        # the store's states score the episode up to its last stroke, which it does not hold
        assert episode_scores(data["state"], np.array([len(data["state"])]))[0] == pytest.approx(
            geometry.f1_from_summary(data["state"][-1, 8:]))
    vertices = [initial_scene(s) for s in range(100000, 100006)]
    edges = [v[(i + 1) % 3] - v[i] for v, i in vertices]
    turns = [np.sign(e[0] * f[1] - e[1] * f[0]) for e, f in zip(edges, firsts)]  # which way the first stroke leaves
    assert len(set(turns)) == 2  # some go round one way, some the other
    a, sa = record_episode(DrawExpert(), 100004, RecordConfig(max_steps=30))
    b, sb = record_episode(DrawExpert(), 100004, RecordConfig(max_steps=30))
    assert sorted(a) == ["action", "img", "n_contacts", "state"] and sa == sb
    assert all(a[k].tobytes() == b[k].tobytes() for k in a)


def test_exploration_spreads_the_score_and_inks_off_the_outline() -> None:
    result = evaluate_explore(range(50000, 50006), ExploreConfig(mode="mixed"), max_steps=120)
    quantiles = result["score_quantiles"]
    assert quantiles[100] - quantiles[0] > 0.3 and result["mean_final_off_outline"] > 0.1
    assert sum(result["modes"].values()) == 6 and sum(n > 0 for n in result["modes"].values()) > 1
    scribbles = evaluate_explore(range(50000, 50006), ExploreConfig(mode="scribbles"), max_steps=120)
    # scribbling alone inks further off the outline, and scores lower, than the mix on the same seeds
    assert scribbles["mean_final_off_outline"] > result["mean_final_off_outline"]
    assert scribbles["mean_score"] < result["mean_score"]
