"""LeRobot and Diffusion Policy checkpoints as gpc policies: equivalence, the restricted unpickler, bad input.

The fixtures (``tests/fixtures/foreign``, made by ``make_fixtures.py`` with LeRobot 0.4.4 and
Diffusion Policy's own code in a throwaway environment) hold small real checkpoints of each
format, observation histories, the initial noise and the chunks the original code sampled.
gpc's chunks must equal them: to 1e-4 in the normalised action space the networks work in,
and to 1e-4 of the action range in pixels (float32 rounding of a 100-step chain, ~5e-6
normalised, is amplified ~250x by the 512 px workspace; that is all that differs).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.errors import DataError
from gpc.harness.policies import describe, load_policy
from gpc.models.policy.formats import detect_format
from gpc.models.policy.formats.safetensors import encode_safetensors, read_safetensors

pytestmark = pytest.mark.usefixtures("one_thread")
FIXTURES = Path(__file__).parent / "fixtures" / "foreign"
cli = CliRunner()


def _formula():
    spec = importlib.util.spec_from_file_location("weights_formula", FIXTURES / "weights_formula.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("weights_formula", module)
    spec.loader.exec_module(module)
    return module


def _state_dict(src: Path, seed: int | None = None) -> dict[str, torch.Tensor]:
    """A formula-weight case's full state dict: keys.json's keys from the formula, ``kept.npz`` as kept, aliases shared."""
    doc = json.loads((src / "keys.json").read_text())
    keys = [(k, tuple(shape)) for k, shape, _ in doc["keys"]]
    kept = dict(np.load(src / "kept.npz")) if (src / "kept.npz").is_file() else {}
    weights = _formula().formula_weights(keys, int(doc["formula_seed"] if seed is None else seed), keep=set(doc.get("keep", [])))
    state = {k: torch.from_numpy(np.asarray(v)) for k, v in {**weights, **kept}.items()}
    state.update({alias: state[canonical] for alias, canonical in doc.get("aliases", {}).items()})
    return state


def materialise(case: str, tmp: Path) -> Path:
    """The case's policy: its files, with formula weights rebuilt from keys.json (the ~45 MB are not committed).

    A Diffusion Policy case gets a ``.ckpt`` of plain dicts (its config from cfg.yaml, the EMA weights the
    reference sampled with, other non-EMA weights): the real dill/OmegaConf container is ``dp_lowdim``'s."""
    src = FIXTURES / case
    if not (src / "keys.json").is_file():
        return next((src / "checkpoints").glob("*.ckpt")) if (src / "checkpoints").is_dir() else src
    dst = tmp / case
    shutil.copytree(src, dst)
    if (src / "config.json").is_file():
        (dst / "model.safetensors").write_bytes(encode_safetensors(_state_dict(src)))
        return dst
    yaml = pytest.importorskip("yaml", reason="the Diffusion Policy image case reads its cfg.yaml")
    cfg = yaml.safe_load((src / "cfg.yaml").read_text())
    normalizer = {k: torch.from_numpy(v) for k, v in np.load(src / "normalizer.npz").items()}
    ema, model = _state_dict(src), {**_state_dict(src, seed=21), **normalizer}
    torch.save({"cfg": cfg, "state_dicts": {"model": model, "ema_model": {**ema, **normalizer}}, "pickles": {}}, dst / "latest.ckpt")
    return dst / "latest.ckpt"


def gpc_obs(ref, policy) -> dict[str, torch.Tensor]:
    """The reference's observation history under the task's keys (Push-T: state, vertex, keypoint, img)."""
    obs: dict[str, np.ndarray] = {}
    b, t = next(v.shape[:2] for k, v in ref.items() if k.startswith("obs/"))
    state = np.zeros((b, t, 5), np.float32)
    for name in (k[4:] for k in ref if k.startswith("obs/")):
        value = ref[f"obs/{name}"]
        if name in ("observation.state", "agent_pos"):
            state[..., :2] = value
        elif name == "observation.environment_state":
            obs["vertex"] = value.reshape(b, t, 8, 2)
        elif name == "obs":  # Diffusion Policy's low-dim Push-T: 9 keypoints, then the agent
            obs["keypoint"] = value[..., :18].reshape(b, t, 9, 2)
            state[..., :2] = value[..., 18:20]
        elif name in ("observation.image", "image"):
            obs["img"] = np.round(np.moveaxis(value, 2, -1) * 255).astype(np.uint8)
    obs["state"] = state
    return {k: torch.as_tensor(obs[k]) for k in policy.obs_keys}


CASES = sorted(p.name for p in FIXTURES.iterdir() if (p / "reference.npz").is_file()) if FIXTURES.is_dir() else []


@pytest.mark.parametrize("case", CASES)
def test_sampled_chunks_equal_the_original_implementation(case, tmp_path):
    ref = dict(np.load(FIXTURES / case / "reference.npz"))
    policy = load_policy(materialise(case, tmp_path))
    chunk = policy.sample_batch(gpc_obs(ref, policy), 1, torch.Generator().manual_seed(int(ref["seed"])))[:, 0]
    want = torch.as_tensor(ref["chunk"])
    normalized = (policy.normalizer.normalize("action", chunk) - policy.normalizer.normalize("action", want)).abs().max()
    assert float(normalized) < 1e-4, f"{case}: normalised chunks differ by {float(normalized):.2e}"
    half_range = 1.0 / policy.normalizer.scales["action"].abs().min()
    assert float((chunk - want).abs().max()) < 1e-4 * float(half_range) * 2
    executed = chunk[:, policy.action_slice]
    assert torch.allclose(executed, torch.as_tensor(ref["action"]), atol=1e-4 * float(half_range) * 2, rtol=0)
    # K proposals in one batched call: the first history's K=3 draws differ from each other
    many = policy.sample_batch(gpc_obs(ref, policy), 3, torch.Generator().manual_seed(1))
    assert many.shape[:2] == (want.shape[0], 3) and float(many[0].std(dim=0).max()) > 1e-3


@pytest.mark.parametrize("case", [c for c in CASES if c.startswith("lerobot")])
def test_inspect_describes_what_was_loaded(case, tmp_path):
    path = materialise(case, tmp_path)
    result = cli.invoke(app, ["inspect", str(path), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    meta = json.loads((FIXTURES / case / "meta.json").read_text())
    assert info["format"] == "lerobot" and info["horizon"] == meta["horizon"] and info["n_obs_steps"] == meta["n_obs_steps"]
    assert info["sampler"]["method"] == meta["sampler"]["kind"].lower()
    assert info["sampler"]["steps"] == (meta["sampler"].get("num_inference_steps") or 100)
    assert info["parameters"] > 0 and "action" in info["normalizer_ranges"]
    table = cli.invoke(app, ["inspect", str(path)])
    assert table.exit_code == 0 and "observation.state" in table.output


def test_the_three_lerobot_generations_are_told_apart():
    found = {c: describe(load_policy(FIXTURES / c))["generation"] for c in CASES if c.startswith("lerobot_keypoints")}
    want = {"lerobot_keypoints": "processors", "lerobot_keypoints_ddpm_v03": "buffers", "lerobot_keypoints_v01": "flat"}
    assert found == {k: v for k, v in want.items() if k in found} and found


def test_outline_vertices_are_gym_pushts_environment_state():
    """LeRobot's keypoint policies read gym-pusht's 8 vertices, in pymunk's order for the T's two boxes."""
    from gpc.tasks.pusht import geometry
    from gpc.tasks.pusht.sim import PushTSim

    sim = PushTSim()
    boxes = sorted((list(map(tuple, s.get_vertices())) for s in sim.block.shapes), key=lambda v: min(p[1] for p in v))
    assert [p for box in boxes for p in box] == [tuple(v) for v in geometry.OUTLINE_VERTICES]
    pose = np.array([200.0, 300.0, 0.7])
    world = geometry.outline_vertices(pose)
    c, s = np.cos(0.7), np.sin(0.7)
    x, y = geometry.OUTLINE_VERTICES[3]
    assert np.allclose(world[3], [200 + c * x - s * y, 300 + s * x + c * y])


def test_safetensors_reader_and_writer_agree_with_the_package(tmp_path):
    tensors = {"a.weight": torch.randn(3, 4), "b": torch.arange(5, dtype=torch.int64), "c": torch.randn(2).to(torch.bfloat16),
               "empty": torch.zeros(0)}
    path = tmp_path / "t.safetensors"
    path.write_bytes(encode_safetensors(tensors, {"format": "pt"}))
    back = read_safetensors(path)
    assert set(back) == set(tensors) and all(torch.equal(back[k], tensors[k]) for k in tensors)
    st = pytest.importorskip("safetensors.torch", reason="the safetensors package (a dev dependency) cross-checks the format")
    theirs = st.load_file(str(path))
    assert all(torch.equal(theirs[k], tensors[k]) for k in tensors)
    st.save_file({"x": torch.randn(7, 3)}, str(tmp_path / "u.safetensors"))
    assert read_safetensors(tmp_path / "u.safetensors")["x"].shape == (7, 3)
    path.write_bytes(path.read_bytes()[:-8])  # truncated
    with pytest.raises(DataError, match="t.safetensors.*does not fit"):
        read_safetensors(path)


class Evil:
    """Unpickling this runs a shell command (what a crafted checkpoint would do)."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


class EvalEvil:
    def __init__(self, code):
        self.code = code

    def __reduce__(self):
        return eval, (self.code,)


@pytest.mark.parametrize("make", [lambda m: Evil(f"touch {m}"), lambda m: EvalEvil(f"open({str(m)!r}, 'w').close()")],
                         ids=["os.system", "builtins.eval"])
def test_a_crafted_ckpt_runs_no_code(tmp_path, make):
    marker = tmp_path / "pwned"
    ckpt = tmp_path / "crafted.ckpt"
    torch.save({"cfg": {"policy": make(marker)}, "state_dicts": {"model": {}}, "pickles": {}}, ckpt)
    with pytest.raises(DataError, match="crafted.ckpt: refused to rebuild"):
        load_policy(ckpt, format="diffusion_policy")
    assert not marker.exists()
    result = cli.invoke(app, ["inspect", str(ckpt)])
    assert result.exit_code == 2 and "refused to rebuild" in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1 and not marker.exists()


def test_formats_are_detected(tmp_path):
    assert detect_format(FIXTURES / "lerobot_keypoints") == "lerobot"
    assert detect_format(FIXTURES / "lerobot_keypoints" / "config.json") == "lerobot"
    pretrained = tmp_path / "checkpoints" / "last"
    shutil.copytree(FIXTURES / "lerobot_keypoints", pretrained / "pretrained_model")
    assert detect_format(pretrained) == "lerobot" and load_policy(pretrained).config.horizon == 16
    torch.save({"cfg": {}, "state_dicts": {}, "pickles": {}}, tmp_path / "dp.ckpt")
    assert detect_format(tmp_path / "dp.ckpt") == "diffusion_policy"
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="junk.ckpt: not a policy checkpoint"):
        detect_format(tmp_path / "junk.ckpt")


def _edited(tmp_path: Path, edit) -> Path:
    d = tmp_path / "policy"
    shutil.copytree(FIXTURES / "lerobot_keypoints", d)
    edit(d)
    return d


def _config(d: Path, **changes) -> None:
    cfg = json.loads((d / "config.json").read_text())
    for k, v in changes.items():
        if v is None:
            cfg.pop(k, None)
        else:
            cfg[k] = v
    (d / "config.json").write_text(json.dumps(cfg))


def _features(d: Path) -> None:
    cfg = json.loads((d / "config.json").read_text())
    cfg["input_features"]["observation.images.top"] = {"type": "VISUAL", "shape": [3, 96, 96]}
    cfg["input_features"].pop("observation.environment_state")
    (d / "config.json").write_text(json.dumps(cfg))


def _drop_weight(d: Path) -> None:
    weights = read_safetensors(d / "model.safetensors")
    weights.pop(sorted(weights)[0])
    (d / "model.safetensors").write_bytes(encode_safetensors(weights))


STATS = "policy_preprocessor_step_3_normalizer_processor.safetensors"
BAD = [
    ("act", lambda d: _config(d, type="act"), "config.json: policy type 'act' is not supported"),
    ("vqbet", lambda d: _config(d, type="vqbet"), "policy type 'vqbet' is not supported"),
    ("pi0", lambda d: _config(d, type="pi0"), "policy type 'pi0' is not supported"),
    ("no-config", lambda d: (d / "config.json").unlink(), "a directory without config.json"),
    ("malformed-config", lambda d: (d / "config.json").write_text("{not json"), "config.json: not valid JSON"),
    ("missing-horizon", lambda d: _config(d, horizon=None), "config.json has no 'horizon'"),
    ("wrong-dims", lambda d: _config(d, down_dims=[64, 128]), "the weights do not match the config"),
    ("missing-weight", _drop_weight, "the weights do not match the config: 1 missing"),
    ("no-weights", lambda d: (d / "model.safetensors").unlink(), "model.safetensors: missing"),
    ("camera-the-task-lacks", _features, "reads 'observation.images.top', which task 'pusht' cannot provide"),
    ("bad-mode", lambda d: _config(d, normalization_mapping={"STATE": "LOG"}), "normalises 'observation.state' with 'LOG'"),
    ("damaged-stats", lambda d: (d / STATS).write_bytes(b"\x01" + b"\0" * 7 + b"{" + b"\0" * 16),
     "normalizer_processor.safetensors: damaged safetensors header"),
]


@pytest.mark.parametrize("name,edit,expect", BAD, ids=[b[0] for b in BAD])
def test_bad_policy_files_are_one_line_exit_2(tmp_path, name, edit, expect):
    d = _edited(tmp_path, edit)
    before = {p: p.read_bytes() for p in d.iterdir()}
    out = tmp_path / "results"
    result = cli.invoke(app, ["eval", str(d), "--seeds", "100000:100001", "--max-steps", "2", "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert expect in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1, result.output
    assert {p: p.read_bytes() for p in d.iterdir()} == before and not (out / "summary.json").exists()


def test_a_lerobot_policy_runs_closed_loop_in_gpcs_environment(tmp_path):
    """The harness derives gym-pusht's vertices from gpc's state every step; the result records the format."""
    out = tmp_path / "bc"
    result = cli.invoke(app, ["eval", str(FIXTURES / "lerobot_keypoints"), "--seeds", "100000:100002", "--max-steps", "24",
                              "--out", str(out), "--policy-format", "lerobot", "--task", "pusht"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller"]["policy_format"] == "lerobot"
    episodes = json.loads((out / "episodes.json").read_text())
    assert [e["seed"] for e in episodes] == [100000, 100001] and all(e["steps"] == 24 for e in episodes)


def test_load_planner_takes_a_foreign_policy_with_its_task(tmp_path):
    from gpc.datasets.normalizer import MinMaxNormalizer
    from gpc.models.planning.config import PlannerConfig
    from gpc.models.planning.loading import load_planner
    from gpc.models.rewards.registration import RegistrationReward
    from gpc.models.world_models.module import WorldModelModule
    from gpc.models.world_models.profiles import world_model_profile
    from gpc.tasks import get_task

    task = get_task("pusht")
    reward = RegistrationReward.from_layout(task.layout)
    state_wm = WorldModelModule(world_model_profile("tiny", 1, task.layout).config, normalizer=MinMaxNormalizer())
    config = PlannerConfig(kind="rank", num_proposals=4, action_low=0.0, action_high=512.0)
    with pytest.raises(ValueError, match="needs the task it acts in"):
        load_planner(FIXTURES / "lerobot_keypoints", state_wm, reward, config)
    planner = load_planner(FIXTURES / "lerobot_keypoints", state_wm, reward, config, task=task)
    assert {"state", "vertex"} <= set(planner.obs_keys)
    if "lerobot_image" in CASES:  # an image policy with a state-only world model: refused in one line
        with pytest.raises(DataError, match="a state world model cannot plan for a image policy"):
            load_planner(materialise("lerobot_image", tmp_path), state_wm, reward, config, task=task)
