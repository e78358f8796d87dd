"""State world model end to end on CPU: synthetic Zarr stores, both training phases, rollouts, CLI."""

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
import gpc.models.world_models.module as wm_module
from gpc.cli.main import app
from gpc.cli.world_model import world_model_app
from gpc.datasets.datamodule import EpisodeDataModule
from gpc.datasets.errors import DataError
from gpc.datasets.sequence import HeldOutOf
from gpc.datasets.store import EpisodeStore
from gpc.models.planning.protocols import WorldModel
from gpc.models.rewards.registration import RegistrationReward
from gpc.models.training.checkpoint import checkpoint_meta
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import TrainingDiverged, train
from gpc.models.world_models.config import WorldModelConfig
from gpc.models.world_models.eval_state import evaluate_rollouts
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks.pusht import LAYOUT

TEE = torch.tensor([[-60, 30], [60, 30], [60, 0], [-60, 0], [-15, 30], [-15, 120], [15, 120], [15, 30]], dtype=torch.float32)
GOAL = torch.tensor([256.0, 256.0, math.pi / 4])


def make_store(path: Path, episodes: int = 8, length: int = 50, seed: int = 0, nan: bool = False) -> Path:
    """Push-T-like dynamics: the agent moves 40% of the way to its action; a nearby block is dragged
    along and turned by the agent's horizontal motion (angles cross 0 / 2 pi inside episodes)."""
    rng = np.random.default_rng(seed)
    store = EpisodeStore.create(path, {"task": "pusht"})
    for e in range(episodes):
        p, b = rng.uniform(150, 350, 2), 256.0 + rng.uniform(-40, 40, 2)
        th, goal = rng.uniform(-0.5, 0.5), p
        states, actions = [], []
        for t in range(length):
            if t % 10 == 0:
                goal = rng.uniform(150, 350, 2)
            a = p + np.clip(goal - p, -30, 30) + rng.normal(0, 3, 2)
            states.append([*p, *b, th % (2 * np.pi)])
            actions.append(a)
            p_new = p + 0.4 * (a - p)
            if np.linalg.norm(p - b) < 90:
                b, th = b + 0.3 * (p_new - p), th + 0.006 * (p_new - p)[0]
            p = p_new
        state = np.array(states, np.float32)
        if nan and e == episodes - 1:
            state[3, 2] = np.nan
            data = {"state": np.nan_to_num(state), "action": np.array(actions, np.float32)}
            store.append_episode(data, seed=e)
            import zarr

            zarr.open_group(str(path), mode="r+")["data/state"][store.n_steps - length + 3, 2] = np.nan
            continue
        store.append_episode({"state": state, "action": np.array(actions, np.float32)}, seed=e)
    return path


def run(tmp: Path, name: str, **kw) -> RunConfig:
    kw = {"max_steps": 4, "batch_size": 32, "progress": False, "accelerator": "cpu", "val_ratio": 0.25, **kw}
    return RunConfig(run_dir=tmp / name, **kw)


def tiny(phase: int = 1, **kw) -> WorldModelConfig:
    return dataclasses.replace(world_model_profile("tiny", phase, LAYOUT).config, **kw)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return make_store(tmp_path_factory.mktemp("data") / "synth.zarr")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("runs")


@pytest.fixture(scope="module")
def phase1(store, runs):
    return train(WorldModelModule, tiny(1), [store], run(runs, "wm-phase1", max_steps=80, checkpoint_every=40))


@pytest.fixture(scope="module")
def phase2(store, runs, phase1):
    return train(WorldModelModule, tiny(2), [store], run(runs, "wm-phase2", max_steps=40), init=phase1.last)


def _batch(store: Path, config: WorldModelConfig) -> dict[str, torch.Tensor]:
    data = EpisodeDataModule(WorldModelModule.data_config(config, (str(store),), run(Path("/unused"), "x", batch_size=128), (0, 0.25)))
    return next(iter(data.train_dataloader()))


def _loss(module: WorldModelModule, batch, unroll: int, units: str = "delta") -> float:
    h, t = module.n_obs_steps, module.config.horizon
    with torch.no_grad():
        return float(module.dynamics.loss(batch["state"], batch["action"][:, h - 1 : h - 1 + t], unroll, units)[0])


def _history(store: Path, episode: int = 0, step: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
    ep = EpisodeStore.open(store).episode(episode)
    return torch.from_numpy(ep["state"][step - 1 : step + 1]), torch.from_numpy(ep["action"][step : step + 8])


def test_phase_one_loss_decreases(phase1, store):
    batch = _batch(store, phase1.module.config)
    fresh = WorldModelModule(phase1.module.config, normalizer=phase1.module.dynamics.normalizer)
    before, after = _loss(fresh, batch, 1), _loss(phase1.module, batch, 1)
    assert phase1.global_step == 80
    assert after < 0.4 * before, (before, after)  # in units of the one-step delta's variance (about 0.25 here)
    assert phase1.best is not None and phase1.best_val_loss < 0.5 * before
    windows = batch["state"]
    assert windows.shape[1:] == (2 + 8, 5) and batch["action"].shape[1:] == (10, 2)


def test_phase_two_starts_from_phase_one_weights(phase1, store, runs, monkeypatch):
    monkeypatch.setattr(wmt, "fit_module", lambda module, *args, **kw: module)  # build, do not train
    start = train(WorldModelModule, tiny(2, dynamics=dataclasses.replace(tiny().dynamics, width=64)), [store],
                              run(runs, "p2-start"), init=phase1.last)
    assert start.config.dynamics == phase1.module.config.dynamics  # phase 1's network wins over the profile's
    assert start.config.phase == 2 and start.config.unroll_steps == 8
    want, got = phase1.module.state_dict(), start.state_dict()
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)


def test_a_run_started_from_a_checkpoint_holds_out_its_episodes_whatever_its_seed(phase1, store, runs, monkeypatch):
    built = []
    monkeypatch.setattr(wmt, "fit_module", lambda module, data, *args, **kw: built.append(data) or module)
    train(WorldModelModule, tiny(2), [store], run(runs, "p2-seed", seed=7), init=phase1.last)
    first = EpisodeDataModule(WorldModelModule.data_config(phase1.module.config, (str(store),), run(runs, "x"), (0, 0.25)))
    assert list(built[0].val_episodes) == list(first.val_episodes)
    other = EpisodeDataModule(WorldModelModule.data_config(phase1.module.config, (str(store),), run(runs, "x"), (7, 0.25)))
    assert list(other.val_episodes) != list(first.val_episodes)  # seed 7 alone would hold out others
    record = json.loads((runs / "p2-seed" / "run.json").read_text())
    assert (record["seed"], record["split_seed"]) == (7, 0)


def test_phase_two_lowers_the_unrolled_loss(phase1, phase2, store):
    batch = _batch(store, phase1.module.config)
    before, after = _loss(phase1.module, batch, 8, "state"), _loss(phase2.module, batch, 8, "state")
    assert phase2.global_step == 40 and after < 0.8 * before, (before, after)
    ckpt = torch.load(phase2.last, weights_only=True)
    assert ckpt["gpc"] == {"format": 1, "kind": "world_model", "task": "pusht", "obs": "state", "phase": 2}
    assert ckpt["hyper_parameters"]["data"]["init"] == str(phase1.last)
    record = json.loads((phase2.run_dir / "run.json").read_text())
    assert record["kind"] == "world_model" and record["config"]["phase"] == 2


def test_batched_rollouts_equal_one_by_one_and_broadcast(phase2, store):
    model = WorldModelModule.load_from_checkpoint(phase2.last)
    assert isinstance(model, WorldModel) and not model.training
    histories = torch.stack([_history(store, e, s)[0] for e, s in ((0, 5), (1, 20), (2, 30))])
    actions = torch.stack([_history(store, e, s)[1] for e, s in ((0, 5), (1, 20), (2, 30))])
    with torch.no_grad():
        together = model.rollout(histories, actions)
        alone = torch.cat([model.rollout(histories[i : i + 1], actions[i : i + 1]) for i in range(3)])
        broadcast = model.rollout(histories[0], actions)
        expanded = model.rollout(histories[:1].expand(3, -1, -1), actions)
    assert together.shape == (3, 8, 5) and torch.allclose(together, alone, atol=1e-4)
    assert torch.allclose(broadcast, expanded, atol=1e-5)
    assert (together[..., 4] >= 0).all() and (together[..., 4] < 2 * math.pi).all()
    trained = phase2.module.eval()
    with torch.no_grad():
        assert torch.equal(trained.rollout(histories, actions), together)  # the checkpoint round trip is exact
    with pytest.raises(ValueError, match=r"actions: expected \(K, T, 2\)"):
        model.rollout(histories, actions[..., :1])


def test_rollout_and_reward_are_differentiable_in_the_actions(phase2, store):
    model = phase2.module.eval()
    history, actions = _history(store)
    actions = actions.expand(4, -1, -1).clone().requires_grad_(True)
    score = RegistrationReward(TEE, GOAL, LAYOUT.pose_dims)(model.rollout(history, actions))
    score.sum().backward()
    assert score.shape == (4,) and torch.isfinite(actions.grad).all()
    assert actions.grad.abs().sum() > 0 and actions.grad[:, 0].abs().sum() > 0  # the first action matters


def test_angles_near_zero_and_two_pi_predict_the_same(phase1):
    model = phase1.module.eval()
    base = torch.tensor([[250.0, 220.0, 260.0, 250.0, 0.0]] * 2)
    low, high = base.clone(), base.clone()
    low[:, 4], high[:, 4] = 0.01, 2 * math.pi - 0.01
    actions = torch.tensor([[[255.0, 240.0]] * 4])
    with torch.no_grad():
        a, b = model.rollout(low, actions), model.rollout(high, actions)
    turn = torch.remainder(a[..., 4] - b[..., 4] + math.pi, 2 * math.pi) - math.pi
    assert torch.allclose(a[..., :4], b[..., :4], atol=0.5), (a, b)
    assert (turn - 0.02).abs().max() < 0.02, turn  # apart by the inputs' 0.02 rad, no 2 pi jump


def test_wrong_kind_checkpoint_and_nan_data_are_one_line_errors(phase1, store, runs, tmp_path):
    ckpt = torch.load(phase1.last, weights_only=True)
    ckpt["gpc"] = checkpoint_meta("policy", "pusht", obs="state")
    torch.save(ckpt, tmp_path / "policy.ckpt")
    for call in (lambda: WorldModelModule.load_from_checkpoint(tmp_path / "policy.ckpt"),
                 lambda: train(WorldModelModule, tiny(2), [store], run(tmp_path, "p2"), init=tmp_path / "policy.ckpt")):
        with pytest.raises(DataError, match="is a 'policy' checkpoint, expected a 'world_model' checkpoint") as err:
            call()
        assert "\n" not in str(err.value)
    bad = make_store(tmp_path / "nan.zarr", episodes=3, nan=True)
    with pytest.raises(DataError, match=r"nan.zarr: data/state holds NaN or inf") as err:
        train(WorldModelModule, tiny(1), [bad], run(tmp_path, "nan"))
    assert "\n" not in str(err.value)
    with pytest.raises(DataError, match="phase 2 starts from phase-1 weights"):
        train(WorldModelModule, tiny(2), [store], run(tmp_path, "noinit"))
    with pytest.raises(DataError, match="is phase 1, not phase 2"):
        train(WorldModelModule, tiny(2), [store], run(runs, "wm-phase1", resume=True))


def test_a_store_of_another_state_size_is_refused_in_one_line(phase1, store, tmp_path):
    wide = tmp_path / "wide.zarr"
    src, out = EpisodeStore.open(store), EpisodeStore.create(wide, {"task": "pusht"})
    for e in range(3):
        ep = src.episode(e, ["state", "action"])
        out.append_episode({"state": np.concatenate([ep["state"], ep["state"][:, :1]], axis=1), "action": ep["action"]}, seed=e)
    with pytest.raises(DataError, match=r"wide.zarr: data/state rows are \(6,\), the world model needs \(5,\)") as err:
        train(WorldModelModule, tiny(2), [wide], run(tmp_path, "p2"), init=phase1.last)
    assert "\n" not in str(err.value) and not (tmp_path / "p2" / "checkpoints").exists()


@pytest.mark.parametrize("where", ["history", "actions"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_rollout_refuses_non_finite_inputs(phase1, where, bad):
    model = WorldModelModule.load_from_checkpoint(phase1.last)
    history, actions = torch.full((model.n_obs_steps + 2, 5), 200.0), torch.full((2, 4, 2), 200.0)
    history[0, 4] = bad  # older than the model reads: ignored
    assert torch.isfinite(model.rollout(history, actions)).all()
    (history[-1:, 4] if where == "history" else actions[1, 2, :1]).fill_(bad)
    with pytest.raises(ValueError, match="NaN or inf"):
        model.rollout(history, actions)


def test_non_finite_loss_stops_training(store, tmp_path, monkeypatch):
    real, calls = wm_module.WorldModelModule.loss, {"n": 0}

    def going_nan(self, batch):
        loss, logs = real(self, batch)
        calls["n"] += self.training
        return (loss * float("nan") if self.training and calls["n"] > 2 else loss), logs

    monkeypatch.setattr(wm_module.WorldModelModule, "loss", going_nan)
    with pytest.raises(TrainingDiverged, match="non-finite at step 2"):
        train(WorldModelModule, tiny(1), [store], run(tmp_path, "nan", max_steps=10))
    ckpt = torch.load(tmp_path / "nan" / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["global_step"] <= 3 and all(torch.isfinite(v).all() for v in ckpt["state_dict"].values())


def test_resume_continues_phase_one(store, tmp_path):
    first = train(WorldModelModule, tiny(1), [store], run(tmp_path, "r", max_steps=3))
    second = train(WorldModelModule, tiny(1), [store], run(tmp_path, "r", max_steps=6, resume=True))
    assert (first.global_step, second.global_step) == (3, 6)
    assert torch.load(second.last, weights_only=True)["global_step"] == 6


def test_cli_trains_both_phases_and_evaluates(store, tmp_path, phase1):
    cli = CliRunner()
    common = ["--dataset", str(store), "--profile", "tiny", "--max-steps", "3", "--batch-size", "16",
              "--accelerator", "cpu", "--no-progress"]
    ok = cli.invoke(world_model_app, ["train", "--out", str(tmp_path / "wm-phase1"), *common])
    assert ok.exit_code == 0, ok.output
    two = cli.invoke(world_model_app, ["train", "--phase", "2", "--out", str(tmp_path / "wm-phase2"), *common])
    assert two.exit_code == 0, two.output
    assert f"phase 2 starts from {tmp_path / 'wm-phase1' / 'checkpoints' / 'last.ckpt'}" in two.output
    lost = cli.invoke(world_model_app, ["train", "--phase", "2", "--out", str(tmp_path / "elsewhere"), *common])
    assert isinstance(lost.exception, DataError) and "pass --init" in str(lost.exception)
    ckpt = torch.load(phase1.last, weights_only=True)
    ckpt["gpc"]["kind"] = "policy"
    torch.save(ckpt, tmp_path / "policy.ckpt")
    wrong = cli.invoke(world_model_app, ["train", "--phase", "2", "--init", str(tmp_path / "policy.ckpt"),
                                         "--out", str(tmp_path / "p2b"), *common])
    assert isinstance(wrong.exception, DataError) and "is a 'policy' checkpoint" in str(wrong.exception)
    last = tmp_path / "wm-phase2" / "checkpoints" / "last.ckpt"
    ev = cli.invoke(world_model_app, ["eval", str(last), "--dataset", str(store), "--episodes", "1"])
    assert ev.exit_code == 0, ev.output
    report = json.loads((tmp_path / "wm-phase2" / "eval" / "world_model_eval.json").read_text())
    assert report["episodes"] == 1 and report["checkpoint"] == str(last) and len(report["steps"]) == 8
    assert "| 8 |" in ev.output and (tmp_path / "wm-phase2" / "eval" / "world_model_eval.md").is_file()
    image_only = cli.invoke(app, ["eval", "world-model", str(last), "--dataset", str(store), "--sampler-steps", "5"])
    assert image_only.exit_code == 2 and "--sampler-steps applies to image world models only" in image_only.output


def test_phase_one_trains_on_the_human_data(human_data, tmp_path):
    result = train(WorldModelModule, tiny(1), [human_data], run(tmp_path, "human", max_steps=2, batch_size=16, val_ratio=0.05))
    assert result.global_step == 2
    stats = result.module.dynamics.normalizer
    assert set(stats.keys()) == {"state", "action", "state_delta"}
    assert float(1 / stats.scales["state_delta"][4]) < 0.2  # wrapped angle deltas: no 2 pi jumps in the spread


def test_object_frame_sees_a_moved_and_turned_scene_the_same():
    """The block-frame features do not change when the whole scene is shifted and rotated, and the
    predicted block displacement turns with the scene (the only frame-dependent part)."""
    from gpc.models.world_models.config import DynamicsConfig
    from gpc.models.world_models.state import StateDynamics, rotate

    config = DynamicsConfig.for_layout(LAYOUT, "object", width=16, depth=1)
    model = StateDynamics(config)
    model.normalizer.add("state", np.zeros(5), np.full(5, 512.0))
    model.normalizer.add("action", np.zeros(2), np.full(2, 512.0))
    model.normalizer.add("state_delta", np.full(5, -1.0), np.ones(5))
    g = torch.Generator().manual_seed(0)
    history = torch.rand(3, 2, 5, generator=g) * 200 + 150
    action = torch.rand(3, 2, generator=g) * 200 + 150

    def moved(turn: float, shift: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        angle = torch.tensor(turn)
        h = history.clone()
        h[..., 0:2] = rotate(history[..., 0:2], angle) + shift
        h[..., 2:4] = rotate(history[..., 2:4], angle) + shift
        h[..., 4] = history[..., 4] + turn
        return h, rotate(action, angle) + shift

    base = model._object_points(history, action)
    h2, a2 = moved(0.7, torch.tensor([12.0, -30.0]))
    assert torch.allclose(model._object_points(h2, a2), base, atol=1e-4)
    assert base.shape == (3, 2 * config.object_points) and base.abs().sum() > 0
    with torch.no_grad():  # a network that reads only block-frame points: its block displacement turns with the scene
        first = next(m for m in model.net.modules() if isinstance(m, torch.nn.Linear))
        first.weight[:, : config.in_dim - 2 * config.object_points] = 0.0
    step = model.step(history, action) - history[:, -1]
    step2 = model.step(h2, a2) - h2[:, -1]
    assert torch.allclose(step2[:, 2:4], rotate(step[:, 2:4], torch.tensor(0.7)), atol=1e-3)
    assert torch.allclose(step2[:, 4], step[:, 4], atol=1e-4)


def test_two_models_meet_on_the_episodes_one_of_them_held_out(phase1, store, tmp_path):
    other = make_store(tmp_path / "other.zarr", episodes=4, seed=1)
    both = train(WorldModelModule, tiny(1), [store, other], run(tmp_path, "both", max_steps=2))
    held = [e for s, e in both.module.data_record["held_out"] if s == str(other.resolve())]
    assert held, "the split over 12 episodes holds out some of other.zarr's"
    named = HeldOutOf(str(both.last), both.module.data_record)
    # phase1 never saw other.zarr: it is scored on exactly the episodes `both` held out of it.
    report = evaluate_rollouts(phase1.module, [other], layout=LAYOUT, held_out_of=named)
    assert report["episodes"] == len(held) and report["split"] == f"held out by {both.last}"
    assert report["windows"] == evaluate_rollouts(both.module, [other], layout=LAYOUT, split="all",
                                                   episodes=4)["windows"] * len(held) // 4
    # phase1 trained on synth.zarr except its own held-out episodes: `both`'s differ, so some it trained on.
    with pytest.raises(DataError, match=r"synth.zarr episode \d+: held out by .* but in this model's training data") as err:
        evaluate_rollouts(phase1.module, [store, other], layout=LAYOUT, held_out_of=named)
    assert "\n" not in str(err.value)
    cli = CliRunner()
    out = tmp_path / "eval"
    ok = cli.invoke(app, ["eval", "world-model", str(phase1.last), "--dataset", str(other), "--held-out-of", str(both.last),
                          "--out", str(out)])
    assert ok.exit_code == 0, ok.output
    assert f"from {len(held)} episodes held out by {both.last}" in (out / "world_model_eval.md").read_text()
    clash = cli.invoke(app, ["eval", "world-model", str(phase1.last), "--dataset", str(other), "--held-out-of",
                             str(both.last), "--split", "all", "--out", str(tmp_path / "clash")])
    assert clash.exit_code != 0 and "--split all and --held-out-of exclude each other" in clash.output
    unknown = cli.invoke(app, ["eval", "world-model", str(phase1.last), "--dataset", str(other), "--held-out-of",
                               str(phase1.last), "--out", str(tmp_path / "none")])
    assert unknown.exit_code != 0 and "held out no episode of the given stores" in unknown.output


def test_a_3d_object_is_judged_on_its_height_and_reported_in_the_tasks_unit():
    """Block Stacking's red cube lifted 2 cm, nothing else wrong: the height error is 2 cm, the planar one 0, and the
    table shows them in mm (its state is in metres); Push-T's table keeps px."""
    from gpc.models.world_models.eval_state import markdown_table, state_errors
    from gpc.tasks.stack import LAYOUT as STACK

    true = torch.zeros(3, 4, STACK.state.dim)
    pred = true.clone()
    pred[..., STACK.primary.height] += 0.02
    errors = state_errors(pred, true, STACK)
    torch.testing.assert_close(errors["object_height"], torch.full((3, 4), 0.02))
    assert errors["object_px"].abs().max() == 0 and errors["agent_px"].abs().max() == 0
    assert "object_height" not in state_errors(torch.zeros(2, 3, LAYOUT.state.dim), torch.zeros(2, 3, LAYOUT.state.dim), LAYOUT)
    steps = [{"step": 1, "model": {k: float(v.mean()) for k, v in errors.items()}, "baseline": {k: 0.0 for k in errors}}]
    report = {"windows": 3, "split": "val", "episodes": 1, "history": 2, "horizon": 1, "steps": steps,
              "mean_over_steps": steps[0], "unit": STACK.unit, "unit_scale": STACK.unit_scale}
    table = markdown_table(report)
    assert "| object mm | object height mm |" in table and "| 1 | 0.00 / 0.00 | 20.00 / 0.00 |" in table
    assert "| object px |" in markdown_table({**report, "unit": "px", "unit_scale": 1.0})


def test_an_object_height_on_a_pose_entry_is_refused():
    from gpc.datasets.layout import ObjectLayout

    with pytest.raises(ValueError, match="height entry 5 is one of its pose"):
        ObjectLayout(name="red", pose=(4, 5), vertices=((0.0, 0.0),), height=5)
