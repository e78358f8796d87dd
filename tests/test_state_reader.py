"""Vision for a task scored by its own state reward (Triangle Drawing): the image reward reads the whole state from a
frame and scores it with the task's reward; the visual world model's ink is judged pixel by pixel. Real drawings
from the task's expert and renderer, a real (tiny) training."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from gpc.datasets.store import EpisodeStore
from gpc.models.rewards.image_state import StateImageReward, learned_image_reward
from gpc.models.rewards.learned import RewardPredictorConfig, RewardPredictorModule, StatePredictor, reward_profile
from gpc.models.rewards.learned_eval import evaluate_state_reader, state_reader_report
from gpc.models.rewards.registration import RewardConfig
from gpc.models.rewards.state import state_reward
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.eval_visual import visual_markdown_table
from gpc.models.world_models.regions import RegionReadout
from gpc.tasks import get_task
from gpc.tasks.draw import geometry, render
from gpc.tasks.draw.reward import rotations

DRAW, PUSHT = get_task("draw"), get_task("pusht")

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    """Four expert drawings with frames, as `gpc collect --task draw` records them."""
    path = tmp_path_factory.mktemp("data") / "draw.zarr"
    out = EpisodeStore.create(path, {"task": "draw"})
    for seed in range(4):
        arrays, _ = DRAW.record("expert", seed, "fixed", True, 40)
        out.append_episode({k: arrays[k] for k in ("img", "state", "action")}, seed=seed)
    return path


@pytest.fixture(scope="module")
def trained(store, tmp_path_factory):
    config = reward_profile("tiny", DRAW.layout, state_reward=DRAW.state_reward).config
    run = RunConfig(run_dir=tmp_path_factory.mktemp("runs") / "reward", max_steps=12, batch_size=16, progress=False,
                    accelerator="cpu", val_ratio=0.25, val_every=6)
    return train(RewardPredictorModule, config, [store], run)


def test_a_task_scored_by_its_own_reward_gets_a_state_reader_and_push_t_keeps_its_poses():
    draw = reward_profile("tiny", DRAW.layout, state_reward=DRAW.state_reward).config
    assert draw.state_reward == DRAW.state_reward and draw.state_dim == DRAW.layout.state.dim == 33
    assert draw.pose_dims == () and draw.shift_px == 0.0  # a shift moves the pen, not the ink's shares
    pusht = reward_profile("tiny", PUSHT.layout, state_reward=PUSHT.state_reward).config
    assert pusht.state_reward == "" and pusht.pose_dims == PUSHT.layout.pose_dims and pusht.shift_px > 0
    with pytest.raises(ValueError, match="shift_px 0"):
        dataclasses.replace(draw, shift_px=2.0)
    with pytest.raises(ValueError, match="state_dim >= 1"):
        RewardPredictorConfig(task="draw", state_reward=DRAW.state_reward)
    assert draw.agent_dims == DRAW.layout.state.agent_xy == (0, 1) and pusht.agent_dims == ()
    assert draw.point_dims == DRAW.layout.state.points == tuple(range(2, 8))  # the corners
    with pytest.raises(ValueError, match="agent_dims"):
        dataclasses.replace(draw, agent_dims=(0, 40))
    # a checkpoint's config from before the keypoint reads its agent with the head, as it was trained
    old = {k: v for k, v in dataclasses.asdict(draw).items() if k not in ("keypoints", "agent_dims", "point_dims")}
    assert RewardPredictorConfig.from_dict(old).agent_dims == ()


def test_the_agent_is_read_where_the_frame_shows_it_by_the_keypoint_not_the_head():
    """With the head silenced, the pen's entries still follow the pen (the two frames differ only there) and nothing
    else moves; a reader without the keypoint (an older checkpoint's) then reads nothing at all."""
    torch.manual_seed(0)
    vertices, ink = np.array([[100.0, 100.0], [400.0, 120.0], [250.0, 400.0]]), np.zeros((128, 128), bool)
    frames = [render.draw_scene(vertices, ink, np.array(pen), 32) for pen in ([80.0, 250.0], [430.0, 250.0])]
    x = torch.tensor(np.stack(frames)).permute(0, 3, 1, 2).float() / 255.0
    config = reward_profile("tiny", DRAW.layout, state_reward=DRAW.state_reward).config
    for agent_dims in ((0, 1), ()):
        reader = StatePredictor(dataclasses.replace(config, agent_dims=agent_dims, point_dims=())).eval()
        reader.normalizer.scales["img"], reader.normalizer.offsets["img"] = torch.full((3,), 2 / 255), -torch.ones(3)
        reader.normalizer.scales["state"], reader.normalizer.offsets["state"] = torch.ones(33), torch.zeros(33)
        torch.nn.init.zeros_(reader.head[-1].weight)
        torch.nn.init.zeros_(reader.head[-1].bias)
        with torch.no_grad():
            read = reader(x)
        assert read[:, 2:].abs().max() == 0
        assert torch.allclose(read[0, :2], read[1, :2]) is (agent_dims == ())


def test_the_keypoint_map_is_trained_toward_where_it_reads_the_agent():
    """The map's target and its read-out share one geometry (x along columns, y along rows, over the frame's extent):
    a map shaped like the target reads the recorded pen back, and the cross-entropy is lowest on it."""
    config = reward_profile("tiny", DRAW.layout, state_reward=DRAW.state_reward).config
    reader = StatePredictor(dataclasses.replace(config, point_dims=()))
    reader.normalizer.scales["state"], reader.normalizer.offsets["state"] = torch.ones(33), torch.zeros(33)
    states = torch.zeros(3, 33)
    states[:, :2] = torch.tensor([[150.0, 300.0], [250.0, 190.0], [370.0, 330.0]])  # away from the borders
    x = torch.zeros(3, 3, config.input_size, config.input_size)
    cells = config.input_size // 4
    centres = (torch.cartesian_prod(torch.arange(cells), torch.arange(cells)).float() + 0.5) * 512 / cells  # (row, col)

    class Peaked(torch.nn.Module):  # a map peaked where ``pens`` are, a cell wide
        def __init__(self, pens: torch.Tensor) -> None:
            super().__init__()
            self.pens = pens

        def forward(self, early: torch.Tensor) -> torch.Tensor:
            gap = (centres[None] - self.pens.flip(-1)[:, None]).square().sum(-1)
            return (-0.5 * gap / (512 / cells) ** 2).reshape(-1, 1, cells, cells)

    reader.locate = Peaked(states[:, :2])
    read = reader.read(x)[0]
    torch.testing.assert_close(read[:, :2], states[:, :2], atol=8.0, rtol=0)
    right = reader.fit_loss(x, states)[1]["agent_ce"]
    reader.locate = Peaked(states[:, :2].flip(-1))  # rows and columns swapped
    assert reader.fit_loss(x, states)[1]["agent_ce"] > right + 1.0


def test_the_corners_are_the_maps_peaks_moved_by_their_offsets_in_the_heads_order():
    """A heat map peaked at the three corners' cells, offset maps saying where in each cell the corner lies, a head
    that reads each corner 40-60 px off: each corner is read exactly, in the head's order (not the map's); the offset
    loss is nought on those maps and not on maps that say the cells' centres."""
    config = dataclasses.replace(reward_profile("tiny", DRAW.layout, state_reward=DRAW.state_reward).config, input_size=64)
    reader = StatePredictor(config)
    reader.normalizer.scales["state"], reader.normalizer.offsets["state"] = torch.ones(33), torch.zeros(33)
    corners = torch.tensor([[250.0, 420.0], [100.0, 101.0], [407.0, 120.0]])  # not in the map's row-major order
    state = torch.zeros(33)
    state[2:8] = corners.flatten()
    off = state.clone()
    off[2:8] += torch.tensor([40.0, -30.0, -35.0, 45.0, 30.0, 30.0])
    cell = 512 / 16
    rows, cols = (corners[:, 1] // cell).long(), (corners[:, 0] // cell).long()

    class Peaks(torch.nn.Module):  # channel 0 the agent's (unused here), then the corners' heat map and offsets
        def __init__(self, exact: bool) -> None:
            super().__init__()
            self.exact = exact

        def forward(self, early: torch.Tensor) -> torch.Tensor:
            maps = torch.zeros(4, 16, 16)
            maps[1, rows, cols] = 5.0
            if self.exact:
                maps[2, rows, cols] = corners[:, 0] / cell - cols - 0.5
                maps[3, rows, cols] = corners[:, 1] / cell - rows - 0.5
            return maps.expand(len(early), -1, -1, -1)

    reader.locate = Peaks(exact=True)
    torch.nn.init.zeros_(reader.head[-1].weight)
    with torch.no_grad():
        reader.head[-1].bias.copy_(off)
        out, _, head = reader.read(torch.zeros(1, 3, 64, 64))
        torch.testing.assert_close(head[0, 2:8], off[2:8])
        torch.testing.assert_close(out[0, 2:8].reshape(3, 2), corners)  # from 50-58 px off
        exact = reader.fit_loss(torch.zeros(1, 3, 64, 64), state[None])[1]["points_offset"]
        reader.locate = Peaks(exact=False)  # the cells' centres: up to half a cell (16 px) off
        assert (reader.read(torch.zeros(1, 3, 64, 64))[0][0, 2:8].reshape(3, 2) - corners).abs().max() > 10.0
        centres = reader.fit_loss(torch.zeros(1, 3, 64, 64), state[None])[1]["points_offset"]
    assert exact < 1e-10 < 0.5 < centres


def test_the_state_reader_scores_frames_with_the_task_reward(trained, store):
    module = RewardPredictorModule.load_from_checkpoint(trained.last, task="draw")
    predictor = module.predictor
    assert isinstance(predictor, StatePredictor)
    ep = EpisodeStore.open(store).episode(0, ["img", "state"])
    states = torch.from_numpy(ep["state"]).float()
    # labels and back: the read state is in raw units (pen px, ink shares)
    assert torch.allclose(predictor.to_pose(predictor.targets(states)), states, atol=1e-4)
    ink = state_reward(DRAW.state_reward, DRAW.layout, RewardConfig())
    reward = learned_image_reward(trained.last, ink, task="draw")
    assert isinstance(reward, StateImageReward)
    frames = (torch.from_numpy(ep["img"]).permute(0, 3, 1, 2).float() / 255.0)[None].requires_grad_(True)  # (1, T, 3, S, S)
    score = reward(frames)
    read = predictor(frames[0].detach())
    # the drawing's F1 is made from the whole path (the first frame's ink, then where the pen goes): every frame is read
    assert ink.reads_path and torch.allclose(score, ink(read[None]), atol=1e-5)
    score.sum().backward()
    assert frames.grad is not None and all(frames.grad[0, t].abs().sum() > 0 for t in range(frames.shape[1]))


def test_a_reward_of_the_last_state_reads_the_last_frame_alone(trained, store):
    """Each frame read is a network pass: a final-step reward that does not read the path gets one frame per chunk."""
    seen = []

    class LastInk(torch.nn.Module):
        def forward(self, states: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
            seen.append(states.shape[1])
            return states[:, -1, 8:-1].sum(-1)

    frames = EpisodeStore.open(store).episode(0, ["img"])["img"][None, :5]
    frames = torch.from_numpy(frames).permute(0, 1, 4, 2, 3).float() / 255.0
    reader = learned_image_reward(trained.last, LastInk(), task="draw")
    reader(frames)
    learned_image_reward(trained.last, LastInk(), config=RewardConfig(aggregate="discounted"), task="draw")(frames)
    assert seen == [1, 5]


def test_the_state_reader_is_judged_by_the_reward_of_the_recorded_states(trained, store):
    module = RewardPredictorModule.load_from_checkpoint(trained.last, task="draw")
    ink = state_reward(DRAW.state_reward, DRAW.layout, RewardConfig())
    report = evaluate_state_reader(module, [store], ink, split="all")
    recorded = EpisodeStore.open(store)
    truth = np.concatenate([[geometry.f1_from_summary(s[8:]) for s in recorded.episode(i, ["state"])["state"]]
                            for i in range(recorded.n_episodes)])
    assert report["frames"] == len(truth) and report["true_reward_mean"] == pytest.approx(truth.mean(), abs=1e-5)
    assert report["constant_baseline_mae"] == pytest.approx(np.abs(truth - np.median(truth)).mean(), abs=1e-6)
    frames = np.concatenate([recorded.episode(i, ["img"])["img"] for i in range(recorded.n_episodes)])
    states = np.concatenate([recorded.episode(i, ["state"])["state"] for i in range(recorded.n_episodes)])
    with torch.no_grad():  # the reader on every frame, scored by the drawing's reward: the report's error
        read = module.predictor(torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255.0)
        pred = ink(read[:, None]).double().numpy()
    assert report["reward_mae"] == pytest.approx(np.abs(pred - truth).mean(), abs=1e-5)
    # each entry's error against what the frame tells (the corners in the cyclic order nearest the reading)
    recorded = torch.from_numpy(states).float()
    labels = module.predictor.label(recorded, read)
    assert all(any(torch.equal(label, o) for o in options) for label, options in zip(labels, rotations(recorded)))
    gap = [(module.predictor.targets(s) - module.predictor.targets(read)).square().sum(-1) for s in (labels, recorded)]
    assert (gap[0] <= gap[1]).all()
    turned = rotations(recorded)[:, 1]  # a reading near another order of the corners is judged against that order
    assert torch.equal(module.predictor.label(recorded, turned), turned)
    labels = labels.double().numpy()
    np.testing.assert_allclose(report["state_abs_err"], np.abs(read.double().numpy() - labels).mean(axis=0), atol=1e-5)
    assert f"| draw.zarr | all | 4 | {len(truth)} |" in state_reader_report([report])


def _scene(vertices: np.ndarray, cells: list[tuple[int, int]]) -> np.ndarray:
    ink = np.zeros((128, 128), bool)
    for r, c in cells:
        ink[r, c] = True
    return render.draw_scene(vertices, ink, np.array([40.0, 40.0]))


def test_ink_is_judged_pixel_by_pixel_against_nothing_changes():
    readout = RegionReadout.from_layout(DRAW.layout)
    assert readout is not None and RegionReadout.from_layout(PUSHT.layout) is None
    vertices = np.array([[256.0, 100.0], [400.0, 380.0], [110.0, 380.0]])
    def stroke(length: int) -> list[tuple[int, int]]:  # 5 cells (20 px, the pen's width) high, `length` cells long
        return [(25 + r, 60 + c) for c in range(length) for r in range(5)]

    last = _scene(vertices, stroke(10))[None]
    true = np.stack([_scene(vertices, stroke(20)), _scene(vertices, stroke(40))])[None]  # (1, T=2, S, S, 3)
    still = np.repeat(last[:, None], 2, axis=1)
    exact = readout.figures(true, true, last)["ink"]
    assert exact["per_step"]["model"] == [0.0, 0.0] and exact["changing_windows"] == 1
    gained = exact["per_step"]["baseline"]
    assert 0 < gained[0] < gained[1]  # the ink the baseline misses grows with the stroke
    assert gained[1] == pytest.approx(30 * 5 * (4 * 96 / 512) ** 2, rel=0.25)  # 30 x 5 more cells of 4 px at 96 / 512
    lazy = readout.figures(still, true, last)["ink"]  # a model that predicts nothing changes is the baseline
    assert lazy["final_changing"]["ratio"] == pytest.approx(1.0)
    report = {"windows": 1, "episodes": 1, "split": "val", "resolution": 96, "frameskip": 8, "noise": "frozen",
              "sampler": {"steps": 3}, "steps": [{"step": 1, "actions": 8, "model": {"ssim": 1.0, "psnr": 40.0},
                                                  "baseline": {"ssim": 0.9, "psnr": 30.0}},
                                                 {"step": 2, "actions": 16, "model": {"ssim": 1.0, "psnr": 40.0},
                                                  "baseline": {"ssim": 0.9, "psnr": 30.0}}],
              "regions": {"ink": exact}}
    md = visual_markdown_table(report)
    assert "| 2 (16) | 0.0 / " in md and "ink: on the 1 windows where it changes" in md
