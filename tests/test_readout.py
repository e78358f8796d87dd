"""The colour readout of a layout with several objects, on frames the real swap renderer draws from known poses: each
object's position, the cube's angle modulo its symmetry, and the per-object figures a visual world model is judged by."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpc.models.world_models.eval_visual import readout_figures, visual_markdown_table
from gpc.models.world_models.readout import ColourReadout, pose_errors
from gpc.tasks.swap import LAYOUT
from gpc.tasks.swap.render import draw_state

# [agent x, y, cube x, y, angle, sphere x, y], each with its swap goal (cube target = sphere start, and back)
STATES = np.array([[80.0, 420.0, 150.0, 160.0, 0.2, 360.0, 330.0], [430.0, 90.0, 300.0, 250.0, 1.3, 140.0, 390.0],
                   [256.0, 460.0, 380.0, 140.0, 2.9, 180.0, 200.0], [60.0, 60.0, 220.0, 380.0, 4.4, 400.0, 260.0],
                   [470.0, 470.0, 260.0, 120.0, 5.8, 250.0, 330.0]])


def _frames(states: np.ndarray, goals: np.ndarray | None = None) -> np.ndarray:
    goals = np.concatenate([STATES[:, 5:7], STATES[:, 2:4]], axis=1) if goals is None else goals
    return np.stack([draw_state(s, g, 96) for s, g in zip(states, goals)])


def test_each_object_is_read_from_the_swap_renderer():
    readout = ColourReadout.from_layout(LAYOUT)
    assert [o.name for o in readout.objects] == ["cube", "sphere"] and [o.angle for o in readout.objects] == [True, False]
    poses = readout.poses(_frames(STATES))  # the targets are drawn too, as in every recorded frame
    assert poses.shape == (len(STATES), 2, 3)
    assert np.abs(poses[:, 0, :2] - STATES[:, 2:4]).max() < 4.0  # world units: under a pixel of a 96 px frame (5.3)
    assert np.abs(poses[:, 1, :2] - STATES[:, 5:7]).max() < 4.0
    cube = readout.objects[0]
    assert cube.symmetry == 4 and np.degrees(np.abs(cube.turn(poses[:, 0, 2], STATES[:, 4]))).max() < 5.0
    assert np.isnan(poses[:, 1, 2]).all()  # a disc has no angle to read
    # a square turned by a quarter turn is the same square: read the same, and no angle error
    quarter = STATES.copy()
    quarter[:, 4] += math.pi / 2
    assert np.abs(readout.poses(_frames(quarter)) - poses)[:, :, :2].max() < 1e-9
    empty = np.full_like(_frames(STATES[:1]), 255)
    assert np.isnan(readout.poses(empty)).all() and readout.agent_area(empty)[0] == 0


def test_angle_and_vertex_errors_count_the_symmetry():
    cube = ColourReadout.from_layout(LAYOUT).objects[0]
    true = np.array([[100.0, 100.0, 0.1]])
    errors = pose_errors(cube, np.array([[103.0, 104.0, 0.1 + math.pi / 2 + math.radians(2.0)]]), true,
                         ColourReadout.from_layout(LAYOUT).outline(0))
    assert errors["object_units"][0] == pytest.approx(5.0) and errors["object_deg"][0] == pytest.approx(2.0)
    # the vertices of the nearest look-alike pose: 5 units of shift and 2 degrees of a 42.4-unit corner radius
    assert 5.0 < errors["object_vertex_units"][0] < 5.0 + math.radians(2.0) * 42.5
    sphere = ColourReadout.from_layout(LAYOUT).objects[1]
    assert set(pose_errors(sphere, true, true)) == {"object_units"}


def test_figures_and_report_give_every_objects_position_ratio():
    """Stand-in futures with known errors: the cube moves and the "model" predicts it exactly; the sphere moves and
    the model leaves it 20 units off; the figures show each object's own moving windows and ratio."""
    readout = ColourReadout.from_layout(LAYOUT)
    last = STATES
    true = STATES.copy()
    true[:, 2] += 40.0  # both objects move 40 units to the right
    true[:, 5] += 40.0
    model = true.copy()
    model[:, 6] += 20.0  # the model's sphere 20 units below the recorded one
    frames = {k: _frames(v)[:, None] for k, v in (("model", model), ("true", true))}
    ro = readout_figures(readout, frames["model"], frames["true"], _frames(last))
    cube, sphere = ro["objects"]["cube"], ro["objects"]["sphere"]
    assert cube["moving_windows"] == sphere["moving_windows"] == len(STATES)
    assert cube["final_moving"]["ratio"]["object_units"] < 0.05 and cube["final_moving"]["model"]["object_units"] < 2.0
    assert 35.0 < cube["final_moving"]["baseline"]["object_units"] < 45.0
    assert 18.0 < sphere["final_moving"]["model"]["object_units"] < 22.0
    assert sphere["final_moving"]["ratio"]["object_units"] == pytest.approx(
        sphere["final_moving"]["model"]["object_units"] / sphere["final_moving"]["baseline"]["object_units"])
    assert "object_deg" not in sphere["final_moving"]["model"] and "object_deg" in cube["final_moving"]["model"]
    assert ro["final_moving"] == cube["final_moving"]  # the first object's figures lead, as for a single object
    report = {"windows": len(STATES), "episodes": 1, "split": "all", "resolution": 96, "frameskip": 1, "noise": "frozen",
              "sampler": {"steps": 3}, "readout_config": readout.describe(), "readout": ro,
              "steps": [{"step": 1, "actions": 1, "model": {"ssim": 0.9, "psnr": 30.0}, "baseline": {"ssim": 0.8, "psnr": 25.0}}]}
    md = visual_markdown_table(report)
    ratio = f"(ratio {sphere['final_moving']['ratio']['object_units']:.2f})"
    assert f"{len(STATES)} windows where the sphere moves: position error" in md and ratio in md
    assert f"{len(STATES)} windows where the cube moves: position error" in md and "Agent visible in" in md
    assert "| cube units | cube deg | cube vertices | agent visible |" in md  # the per-step columns: the first object
