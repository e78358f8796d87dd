"""The colour readout of a layout with several objects, on frames the real swap renderer draws from known poses: each
object's position, the cube's angle modulo its symmetry, and the per-object figures a visual world model is judged by."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

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


class _PixelReader(torch.nn.Module):
    """A stand-in state reader that reads what ``_encode`` wrote: entry j is pixel (0, j)'s red value x 0.1 m / 255."""

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return frames[:, 0, 0, :18] * 0.1


def _encode(states: np.ndarray) -> np.ndarray:
    """``(..., 18)`` states in [0, 0.1] m -> ``(..., 96, 96, 3)`` uint8 frames ``_PixelReader`` reads back."""
    frames = np.zeros(states.shape[:-1] + (96, 96, 3), np.uint8)
    frames[..., 0, :18, 0] = np.round(states / 0.1 * 255).astype(np.uint8)
    return frames


def test_a_state_reader_judges_a_3d_object_on_its_position_and_height_in_the_tasks_unit():
    """Block Stacking's red cube: two windows of two predicted frames. Window 0 lifts it 51 mm (the model predicts
    the lift 2 cm short); window 1 holds still (the model drifts 10.2 mm sideways): per-step errors, the moving window's
    final-frame ratio, and the table in mm."""
    from gpc.models.world_models.state_readout import StateReadout, state_readout_markdown
    from gpc.tasks.stack import LAYOUT as STACK

    last = np.zeros((2, 18))
    last[:, 4:7] = [0.05, 0.05, 0.02]
    true = np.repeat(last[:, None], 2, axis=1)
    true[0, :, 6] += 0.051  # (a multiple of 0.1 / 255: encoded exactly)
    model = true.copy()
    model[0, :, 6] -= 0.02
    model[1, :, 4] += 0.1 * 26 / 255  # 10.2 mm
    readout = StateReadout(_PixelReader(), STACK, "pixels")
    assert [q.name for q in readout.quantities] == ["red", "red height", "agent"]
    figures = readout.figures(_encode(model), _encode(true), _encode(last), recorded=true)
    height, planar = figures["red height"], figures["red"]
    np.testing.assert_allclose(height["per_step"]["model"], [0.01, 0.01], atol=3e-4)  # 2 cm on one window of two
    np.testing.assert_allclose(height["per_step"]["baseline"], [0.0255, 0.0255], atol=3e-4)
    np.testing.assert_allclose(planar["per_step"]["model"], [0.0051, 0.0051], atol=3e-4)
    assert height["moving_windows"] == planar["moving_windows"] == 1  # the lift: 51 mm > a quarter of the 4 cm cube
    np.testing.assert_allclose(height["final_moving"]["ratio"], 0.02 / 0.051, atol=0.01)
    assert planar["final_moving"]["model"] < 3e-4 and height["reader_error"] < 3e-4
    assert figures["agent"]["per_step"]["model"] == [0.0, 0.0] and "moving_windows" not in figures["agent"]
    lines = state_readout_markdown(figures, readout.describe(), [4, 8])
    assert "| step (actions) | red | red height | agent |" in lines and "| 1 (4) | 5.1 / 0.0 | 10.0 / 25.5 | 0.0 / 0.0 |" in lines
    assert any(line.startswith("red height: on the 1 windows where it moves, the last frame is off by 20.0 mm against 51.0")
               for line in lines)
