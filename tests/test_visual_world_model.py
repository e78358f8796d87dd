"""Visual world model end to end on CPU: rendered Zarr stores, both training phases, rollouts, eval, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import gpc.models.training.trainer as wmt
from gpc.cli.main import app
from gpc.cli.world_model import world_model_app
from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore
from gpc.models.networks.edm import EDMConfig, EulerConfig, karras_sigmas
from gpc.models.planning.protocols import WorldModel
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.config import VisualWorldModelConfig
from gpc.models.world_models.eval_visual import ColourReadout, evaluate_visual_rollouts
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks.pusht import LAYOUT
from gpc.tasks.pusht.render import draw_state

SIZE = 32  # stored frame size (the tiny model works at 16 px)


def make_store(path: Path, episodes: int = 6, length: int = 30, seed: int = 0, size: int = SIZE,
               float_nan: bool = False) -> Path:
    """Rendered Push-T frames of a simple dynamics: the agent moves 40% of the way to its action and drags a
    nearby block along (turning it)."""
    rng = np.random.default_rng(seed)
    store = EpisodeStore.create(path, {"task": "pusht"})
    for e in range(episodes):
        p, b, th = rng.uniform(150, 350, 2), 256.0 + rng.uniform(-30, 30, 2), rng.uniform(-0.5, 0.5)
        goal = b
        states, actions, frames = [], [], []
        for t in range(length):
            if t % 8 == 0:
                goal = b + rng.uniform(-60, 60, 2)
            a = p + np.clip(goal - p, -40, 40)
            state = np.array([*p, *b, th % (2 * np.pi)])
            states.append(state)
            actions.append(a)
            frames.append(draw_state(state, size=size))
            p_new = p + 0.4 * (a - p)
            if np.linalg.norm(p - b) < 90:
                b, th = b + 0.5 * (p_new - p), th + 0.004 * (p_new - p)[0]
            p = p_new
        img = np.stack(frames).astype(np.float32 if float_nan else np.uint8)  # float32 0..255, as the human data
        store.append_episode({"state": np.array(states, np.float32), "action": np.array(actions, np.float32),
                              "img": img}, seed=e)
    if float_nan:  # the store refuses to write NaN; plant one behind its back
        import zarr

        zarr.open_group(str(path), mode="r+")["data/img"][store.n_steps - 3, 0, 0, 0] = np.nan
    return path


def run(tmp: Path, name: str, **kw) -> RunConfig:
    kw = {"max_steps": 4, "batch_size": 8, "progress": False, "accelerator": "cpu", "val_ratio": 0.2, **kw}
    return RunConfig(run_dir=tmp / name, **kw)


def tiny(phase: int = 1, **kw) -> VisualWorldModelConfig:
    return dataclasses.replace(world_model_profile("tiny", phase, LAYOUT, obs="image").config, **kw)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return make_store(tmp_path_factory.mktemp("data") / "frames.zarr")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("runs")


@pytest.fixture(scope="module")
def phase1(store, runs):
    return train(WorldModelModule, tiny(1), [store], run(runs, "vwm-phase1", max_steps=40, checkpoint_every=20))


@pytest.fixture(scope="module")
def phase2(store, runs, phase1):
    return train(WorldModelModule, tiny(2), [store], run(runs, "vwm-phase2", max_steps=6), init=phase1.last)


def _windows(store: Path, model: WorldModelModule, starts=((0, 3), (1, 9), (2, 15))) -> tuple[torch.Tensor, torch.Tensor]:
    """Histories as stored images ``(K, n_obs, S0, S0, 3)`` and raw action chunks ``(K, T, 2)``."""
    n, t, hist, acts = model.n_obs_steps, model.config.horizon, [], []
    for e, s in starts:
        ep = EpisodeStore.open(store).episode(e)
        hist.append(torch.from_numpy(ep["img"][s - n + 1 : s + 1]))
        acts.append(torch.from_numpy(ep["action"][s : s + t]))
    return torch.stack(hist), torch.stack(acts)


def _loss_batch(store: Path, model: WorldModelModule) -> tuple[torch.Tensor, torch.Tensor]:
    """Whole windows: frames ``(K, H + N, 3, S, S)`` in [-1, 1] (every frameskip-th step) and ``(K, T, 2)`` actions."""
    n, t, f = model.n_obs_steps, model.config.horizon, model.config.dynamics.frameskip
    wins, acts = [], []
    for e in range(4):
        ep = EpisodeStore.open(store).episode(e)
        for s in (4, 12, 20):
            wins.append(torch.from_numpy(ep["img"][s - n + 1 : s + t + 1 : f]))
            acts.append(torch.from_numpy(ep["action"][s : s + t]))
    return model.dynamics.frames(torch.stack(wins)) * 2 - 1, torch.stack(acts)


def _fixed_loss(module: WorldModelModule, store: Path, unroll: int = 1) -> float:
    frames, acts = _loss_batch(store, module)
    torch.manual_seed(0)
    with torch.no_grad():
        return float(module.dynamics.loss(frames, acts, unroll)[0])


def test_edm_schedule_and_preconditioning():
    sig = karras_sigmas(3, 2e-3, 5.0, 7.0)  # middle: ((5 ** (1 / 7) + 0.002 ** (1 / 7)) / 2) ** 7
    assert torch.allclose(sig, torch.tensor([5.0, 0.2831, 2e-3, 0.0]), rtol=1e-3)
    from gpc.models.networks.edm import Denoiser

    cs = Denoiser(torch.nn.Identity(), EDMConfig()).conditioners(torch.tensor([0.0, 1.0]))
    s = torch.tensor([0.1, math.sqrt(1.01)])  # sigma with the offset noise folded in
    assert torch.allclose(cs.c_skip, 0.25 / (s**2 + 0.25)) and torch.allclose(cs.c_in, 1 / (s**2 + 0.25).sqrt())
    assert torch.allclose(cs.c_out, s * 0.5 / (s**2 + 0.25).sqrt()) and torch.allclose(cs.c_noise, s.log() / 4)
    with pytest.raises(ValueError, match="sampler noise 'zero'"):
        EulerConfig(noise="zero")


def test_phase_one_trains_and_records_the_frames(phase1, store):
    assert phase1.global_step == 40
    module = phase1.module
    fresh = WorldModelModule(module.config, normalizer=module.dynamics.normalizer)
    before, after = _fixed_loss(fresh, store), _fixed_loss(module, store)
    assert after < 0.7 * before, (before, after)
    ckpt = torch.load(phase1.last, weights_only=True)
    assert ckpt["gpc"] == {"format": 1, "kind": "world_model", "task": "pusht", "obs": "image", "phase": 1}
    assert ckpt["hyper_parameters"]["config"]["dynamics"]["source_size"] == SIZE
    assert module.n_obs_steps == 3 and module.config.window == 7  # H = 2 frames 2 steps apart; T = 4


def test_phase_two_starts_from_phase_one_and_unrolls(phase1, phase2, store, runs, monkeypatch):
    assert phase2.global_step == 6 and phase2.module.config.unroll_steps == 2
    ckpt = torch.load(phase2.last, weights_only=True)
    assert ckpt["gpc"]["phase"] == 2 and ckpt["hyper_parameters"]["data"]["init"] == str(phase1.last)
    monkeypatch.setattr(wmt, "fit_module", lambda module, *args, **kw: module)  # build, do not train
    start = train(WorldModelModule, tiny(2, feedback="sampled"), [store], run(runs, "p2-start"), init=phase1.last)
    assert start.config.dynamics == phase1.module.config.dynamics and start.config.feedback == "sampled"
    want, got = phase1.module.state_dict(), start.state_dict()
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)
    frames, acts = _loss_batch(store, start)
    assert frames.shape[1:] == (4, 3, 16, 16) and acts.shape[1:] == (4, 2)  # 2 context frames + 2 predictions
    loss, logs = start.dynamics.loss(frames, acts, unroll=2, feedback="sampled")
    assert torch.isfinite(loss) and set(logs) == {"loss", "loss_last_step"}


def test_frozen_noise_is_deterministic_and_differentiable(phase1, store):
    model = phase1.module.eval()
    hist, acts = _windows(store, model)
    a = model.rollout(hist, acts)
    b = model.rollout(hist, acts)
    assert a.shape == (3, 2, 3, 16, 16) and torch.equal(a, b)
    assert 0.0 <= float(a.min()) and float(a.max()) <= 1.0
    acts = acts.clone().requires_grad_(True)
    score = model.rollout(hist, acts)[:, -1].sum(dim=(1, 2, 3))  # a differentiable image score per proposal
    score.sum().backward()
    assert torch.isfinite(acts.grad).all() and acts.grad.abs().sum() > 0 and acts.grad[:, 0].abs().sum() > 0
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    with torch.no_grad():
        s1, s2 = model.rollout(hist, acts, noise="sampled", generator=g1), model.rollout(hist, acts, noise="sampled", generator=g2)
        s3 = model.rollout(hist, acts, noise="sampled", generator=g1)
    assert torch.equal(s1, s2) and not torch.equal(s1, s3) and not torch.equal(s1, a)


def test_batched_rollouts_equal_one_by_one(phase2, store):
    model = WorldModelModule.load_from_checkpoint(phase2.last)
    assert isinstance(model, WorldModel) and not model.training and model.n_obs_steps == 3
    hist, acts = _windows(store, model)
    frames = model.dynamics.frames(hist)
    with torch.no_grad():
        together = model.rollout(hist, acts)
        alone = torch.cat([model.rollout(hist[i : i + 1], acts[i : i + 1]) for i in range(3)])
        from_frames = model.rollout(frames, acts)
        broadcast = model.rollout(frames[0], acts)
        expanded = model.rollout(frames[:1].expand(3, -1, -1, -1, -1), acts)
        longer = model.rollout(torch.cat([frames[:, :1], frames], dim=1), acts)  # only the last n_obs_steps are read
        trained = phase2.module.eval().rollout(hist, acts)
    assert torch.allclose(together, alone, atol=1e-5) and torch.equal(together, from_frames)
    assert torch.allclose(broadcast, expanded, atol=1e-5) and torch.equal(longer, together)
    assert torch.equal(trained, together)  # the checkpoint round trip is exact
    with pytest.raises(ValueError, match=r"actions: expected \(K, T, 2\)"):
        model.rollout(frames, acts[..., :1])
    with pytest.raises(ValueError, match=r"history: expected \(K, L >= 3, 3, 16, 16\)"):
        model.rollout(frames[:, :2], acts)
    bad = frames.clone()
    bad[0, 0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        model.rollout(bad, acts)
    with pytest.warns(UserWarning, match="frames are 24 px but the world model was trained on 32 px"):
        small = model.rollout(torch.nn.functional.interpolate(hist[0].float().movedim(-1, 1), size=24).movedim(1, -1), acts)
    assert small.shape == together.shape


def test_eval_reports_figures_and_a_grid(phase2, store):
    report, grid = evaluate_visual_rollouts(phase2.module, [store], split="all", readout=ColourReadout.from_layout(LAYOUT),
                                            stride=4, grid_windows=2)
    assert report["windows"] > 10 and len(report["steps"]) == 2 and report["steps"][1]["actions"] == 4
    for row in report["steps"]:
        for name in ("model", "baseline"):
            assert 0.0 < row[name]["ssim"] <= 1.0 and row[name]["psnr"] > 5.0  # the pose figures are checked below
    ro = report["readout"]
    assert ro["moving_windows"] > 0 and ro["final_moving"]["baseline"]["object_units"] > 5.0
    for name in ("model", "baseline"):  # a briefly trained 16 px model may lose the block (NaN poses) in every frame
        final = ro["final_moving"][name]
        assert final["object_lost"] == 1.0 or 0.0 <= final["object_deg_median"] <= 180.0
        assert 0.0 <= final["object_deg_over_90"] <= 1.0
    assert ro["final_moving"]["baseline"]["object_lost"] == 0.0
    base = ro["final_moving"]["baseline"]  # the vertex error joins position and angle (its geometry is checked below)
    assert 0.0 < base["object_vertex_units"] < float("inf") and "object_vertex_units" in ro["final_moving"]["ratio"]
    assert 0.0 <= ro["agent_visible"]["model"] <= 1.0 and 0.0 <= ro["agent_visible"]["true"] <= 1.0  # at 16 px the agent is
    assert len(ro["agent_visible"]["per_step"]) == 2  # half a pixel wide: its visibility is checked at 96 px below
    assert grid.shape == (2 * (2 * (16 * 3 + 2) + 2), 3 * (16 * 3 + 2), 3) and grid.dtype == np.uint8


def _replaying(module: WorldModelModule, store: Path, shift_px: int = 0):
    """A stand-in rollout that predicts the recorded future frames of the window whose actions it is given
    (optionally with the block pushed ``shift_px`` pixels right): what a perfect model would predict."""
    data = EpisodeStore.open(store)
    actions, images = data.read("action"), torch.from_numpy(data.read("img"))
    f = module.config.dynamics.frameskip

    def rollout(history, acts, **_):
        out = []
        for now, chunk in zip(history[:, -1], np.asarray(acts)):  # the window: its actions and its current frame
            hits = [i for i in range(len(actions) - len(chunk) + 1) if np.array_equal(actions[i : i + len(chunk)], chunk)
                    and torch.equal(module.dynamics.frames(images[i]), now)]
            frames = module.dynamics.frames(images[[hits[0] + f * (j + 1) for j in range(len(chunk) // f)]])
            if shift_px:
                block = (frames - torch.tensor([143, 163, 184]).view(3, 1, 1) / 255).abs().sum(dim=1, keepdim=True) < 0.3
                moved = torch.roll(frames * block, shift_px, dims=-1)
                frames = torch.where(torch.roll(block, shift_px, dims=-1), moved, torch.where(block, 1.0, frames))
            out.append(frames)
        return torch.stack(out)

    return rollout


def test_pose_figures_measure_what_a_planner_reads(phase2, store, monkeypatch):
    """The block-pose figures, checked on stand-in models whose answer is known: a model that predicts the recorded
    future has no pose error at all; one that draws the block 4 px (128 world units at 16 px) to the right is off by
    that much; copying the last frame is the nothing-moves baseline, ratio 1."""
    module, readout = phase2.module, ColourReadout.from_layout(LAYOUT)

    def figures(rollout):
        monkeypatch.setattr(module, "rollout", rollout)
        report, _ = evaluate_visual_rollouts(module, [store], split="all", readout=readout, stride=4, max_windows=24)
        return report["readout"]["final_moving"]

    perfect = figures(_replaying(module, store))
    assert perfect["model"]["object_vertex_units"] == 0.0 and perfect["model"]["object_units"] == 0.0
    assert perfect["baseline"]["object_vertex_units"] > 5.0 and perfect["ratio"]["object_vertex_units"] == 0.0
    shifted = figures(_replaying(module, store, shift_px=4))["model"]
    assert 115.0 < shifted["object_units_median"] < 140.0  # 4 px at 16 px per 512 units: 128 units
    steps = module.config.predicted_steps  # the evaluation hands a rollout its context as frames (K, L, 3, S, S)
    still = figures(lambda history, acts, **_: history[:, -1:].expand(len(acts), steps, *history.shape[2:]))
    assert still["ratio"]["object_vertex_units"] == pytest.approx(1.0)


def test_readout_reads_the_block_pose_from_rendered_frames():
    states = np.array([[100.0, 100.0, 250.0, 260.0, a] for a in (0.3, 1.7, 3.5, 5.9)])
    frames = np.stack([draw_state(s, size=96) for s in states])
    pose = ColourReadout.from_layout(LAYOUT).poses(frames)[:, 0]  # the T, the task's one object
    cy = (3600 * 15 + 2700 * 75) / 6300  # the T's centroid in its body frame is (0, cy)
    centre = states[:, 2:4] + np.stack([-np.sin(states[:, 4]), np.cos(states[:, 4])], axis=1) * cy
    assert np.abs(pose[:, :2] - centre).max() < 3.0
    turn = np.abs((pose[:, 2] - states[:, 4] + np.pi) % (2 * np.pi) - np.pi)
    assert turn.max() < np.deg2rad(3)
    readout = ColourReadout.from_layout(LAYOUT)
    # Its vertices sit about the centroid it reads: placed at the read pose they land on the T's true vertices.
    from gpc.tasks.pusht.geometry import tee_vertices, to_world

    read = to_world(readout.outline(0), pose)
    assert np.abs(read - tee_vertices(states[:, 2:5]).reshape(len(states), 8, 2)).max() < 4.0
    assert (readout.agent_area(frames) > 20).all()  # the agent's disc, about 5 px across at 96 px
    empty = np.full_like(frames[:1], 255)
    assert readout.agent_area(empty)[0] == 0 and np.isnan(readout.poses(empty)).all()


def test_bad_inputs_are_one_line_errors(phase1, store, runs, tmp_path):
    ckpt = torch.load(phase1.last, weights_only=True)
    ckpt["gpc"]["kind"] = "policy"
    torch.save(ckpt, tmp_path / "policy.ckpt")
    with pytest.raises(DataError, match="is a 'policy' checkpoint, expected a 'world_model' checkpoint") as err:
        train(WorldModelModule, tiny(2), [store], run(tmp_path, "p2"), init=tmp_path / "policy.ckpt")
    assert "\n" not in str(err.value)
    state = dict(ckpt, gpc={**ckpt["gpc"], "kind": "world_model", "obs": "state"})
    torch.save(state, tmp_path / "state.ckpt")
    with pytest.raises(DataError, match="has obs 'state', expected 'image'"):
        train(WorldModelModule, tiny(2), [store], run(tmp_path, "p2s"), init=tmp_path / "state.ckpt")
    nan = make_store(tmp_path / "nan.zarr", episodes=2, float_nan=True)
    with pytest.raises(DataError, match=r"nan.zarr: data/img holds NaN or inf"):
        train(WorldModelModule, tiny(1), [nan], run(tmp_path, "nan"))
    other = make_store(tmp_path / "small.zarr", episodes=3, size=24)
    with pytest.raises(DataError, match=r"small.zarr: data/img rows are \(24, 24, 3\), other stores have \(32, 32, 3\)"):
        train(WorldModelModule, tiny(1), [store, other], run(tmp_path, "mixed"))
    with pytest.warns(UserWarning, match="frames are 24 px, the model's earlier training used 32 px; resizing 24 -> 16"):
        result = train(WorldModelModule, tiny(2), [other], run(tmp_path, "p2small", max_steps=1), init=phase1.last)
    assert result.global_step == 1
    assert not (runs / "vwm-phase1" / "checkpoints" / "last.ckpt.tmp").exists()


def test_cli_trains_both_phases_and_evaluates(store, tmp_path):
    cli = CliRunner()
    common = ["--dataset", str(store), "--obs", "image", "--profile", "tiny", "--max-steps", "2", "--batch-size", "4",
              "--accelerator", "cpu", "--no-progress"]
    one = cli.invoke(world_model_app, ["train", "--out", str(tmp_path / "vwm-phase1"), *common])
    assert one.exit_code == 0, one.output
    two = cli.invoke(world_model_app, ["train", "--phase", "2", "--feedback", "sampled", "--out", str(tmp_path / "vwm-phase2"), *common])
    assert two.exit_code == 0, two.output
    assert f"phase 2 starts from {tmp_path / 'vwm-phase1' / 'checkpoints' / 'last.ckpt'}" in two.output
    bad = cli.invoke(app, ["train", "world-model", "--out", str(tmp_path / "x"), *common[:4], "--profile", "huge"])
    assert bad.exit_code == 2 and "visual world model profile 'huge'" in bad.output and len(bad.output.strip().splitlines()) == 1
    last = tmp_path / "vwm-phase2" / "checkpoints" / "last.ckpt"
    ev = cli.invoke(world_model_app, ["eval", str(last), "--dataset", str(store), "--split", "all", "--episodes", "2",
                                      "--stride", "6"])
    assert ev.exit_code == 0, ev.output
    out = tmp_path / "vwm-phase2" / "eval"
    report = json.loads((out / "world_model_eval.json").read_text())
    assert report["episodes"] == 2 and report["checkpoint"] == str(last) and len(report["steps"]) == 2
    assert report["sampler"]["steps"] == 3 and "3 Euler steps" in ev.output
    longer = cli.invoke(world_model_app, ["eval", str(last), "--dataset", str(store), "--split", "all", "--episodes", "2",
                                          "--stride", "6", "--sampler-steps", "5", "--out", str(tmp_path / "eval5")])
    assert longer.exit_code == 0, longer.output
    five = json.loads((tmp_path / "eval5" / "world_model_eval.json").read_text())
    assert five["sampler"]["steps"] == 5 and five["windows"] == report["windows"]
    assert five["config"]["dynamics"]["sampler"]["steps"] == 5  # the recorded config says what was sampled
    assert five["steps"][0]["model"]["ssim"] != report["steps"][0]["model"]["ssim"]  # another chain, another frame
    assert five["steps"][0]["baseline"] == report["steps"][0]["baseline"]
    assert "| 2 (4) |" in ev.output and (out / "world_model_frames.png").stat().st_size > 100
    import cv2

    assert cv2.imread(str(out / "world_model_frames.png")).shape[2] == 3


def test_eval_can_read_poses_with_the_learned_reward_predictor(phase2, store, tmp_path):
    """`--pose-reader`: the block pose read by a (real, briefly trained) reward predictor, as the planner's reward sees it."""
    from gpc.models.rewards.learned import RewardPredictorModule, reward_profile
    from gpc.models.training.config import RunConfig

    config = reward_profile("tiny", LAYOUT).config
    reader = train(RewardPredictorModule, config, [store], RunConfig(run_dir=tmp_path / "reward", max_steps=3, batch_size=8,
                                                               progress=False, accelerator="cpu")).last
    cli = CliRunner()
    ev = cli.invoke(world_model_app, ["eval", str(phase2.last), "--dataset", str(store), "--split", "all", "--episodes", "2",
                                      "--stride", "6", "--pose-reader", str(reader), "--out", str(tmp_path / "eval")])
    assert ev.exit_code == 0, ev.output
    report = json.loads((tmp_path / "eval" / "world_model_eval.json").read_text())
    assert report["readout_config"]["pose"] == "learned" and report["readout_config"]["checkpoint"] == str(reader)
    steps = report["readout"]["per_step"]["model"]["object_units"]
    assert len(steps) == 2 and all(np.isfinite(steps)) and "learned pose predictor" in ev.output


def test_a_distilled_one_step_student_agrees_with_its_three_step_teacher(phase1, store, tmp_path):
    """`--distill`: the student samples in 1 step, nearer the teacher's 3-step frames than the teacher's own 1-step
    chain gets, gradients flow through it, and it plans without the teacher (whose weights stay out of its file)."""
    teacher_path, out = tmp_path / "teacher.ckpt", tmp_path / "student"
    teacher_path.write_bytes(Path(phase1.last).read_bytes())
    res = CliRunner().invoke(app, ["train", "world-model", "--distill", str(teacher_path), "--sampler-steps", "1", "--profile", "tiny",
                                   "--dataset", str(store), "--out", str(out), "--max-steps", "60", "--no-progress",
                                   "--accelerator", "cpu"])
    assert res.exit_code == 0, res.output
    teacher = WorldModelModule.load_from_checkpoint(teacher_path)
    teacher_path.unlink()  # a student plans alone, its file holds no teacher
    assert not any("teacher" in key for key in torch.load(out / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"])
    student = WorldModelModule.load_from_checkpoint(out / "checkpoints" / "last.ckpt")
    conv = next(w for w in student.parameters() if w.dim() == 4)  # a planning student keeps its weights channels-last
    assert student.dynamics.config.sampler.steps == 1 and conv.is_contiguous(memory_format=torch.channels_last)
    history, actions = _windows(store, teacher, starts=((3, 3), (4, 9), (5, 15), (0, 12)))
    with torch.no_grad():
        target = teacher.rollout(history, actions)
        student_frames = student.rollout(history, actions)
        teacher.dynamics.use_sampler(dataclasses.replace(teacher.dynamics.config.sampler, steps=1))
        shortcut = teacher.rollout(history, actions)  # the teacher's own chain cut to one step
    rmse = lambda a, b: float((a - b).pow(2).mean().sqrt())  # noqa: E731
    assert rmse(student_frames, target) < 0.7 * rmse(shortcut, target), (rmse(student_frames, target), rmse(shortcut, target))
    (student.rollout(history, moved := actions.clone().requires_grad_(True)) * torch.linspace(0, 1, 16)).sum().backward()
    assert moved.grad is not None and bool(torch.isfinite(moved.grad).all()) and float(moved.grad.abs().sum()) > 0
    bad = CliRunner().invoke(app, ["train", "world-model", "--distill", str(out / "checkpoints" / "last.ckpt"), "--profile", "tiny",
                                   "--dataset", str(store), "--out", str(tmp_path / "s2")])  # --sampler-steps 1 by default
    assert bad.exit_code != 0 and "the teacher samples in 1; a student takes fewer" in bad.output and "Traceback" not in bad.output
