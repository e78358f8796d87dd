"""`gpc export`: a checkpoint that plans exactly as the trained one, smaller, written without touching anything else."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tiny_planning import histories
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.errors import DataError
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.tasks.pusht import LAYOUT

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[1]


def gpc(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def test_exported_policy_samples_the_same_actions_from_a_quarter_of_the_file(ckpts, tmp_path):
    out = tmp_path / "policy.ckpt"
    mask = os.umask(0o022)
    try:
        r = gpc("export", ckpts["policy"], "--out", out)
    finally:
        os.umask(mask)
    assert r.exit_code == 0, r.output
    assert stat.S_IMODE(out.stat().st_mode) == 0o644  # as any file the user writes: written whole, not private
    assert out.stat().st_size < 0.35 * Path(ckpts["policy"]).stat().st_size  # no optimiser state, no raw copy
    saved = torch.load(out, weights_only=True)
    assert "optimizer_states" not in saved and saved["gpc"]["raw_from_average"] == "model."
    assert not any(k.startswith("model.") for k in saved["state_dict"])
    trained, exported = PolicyModule.load_from_checkpoint(ckpts["policy"]), PolicyModule.load_from_checkpoint(out)
    obs = {k: torch.as_tensor(v) for k, v in histories([200000, 200001]).items()}

    def draw(policy: PolicyModule, **kw) -> torch.Tensor:
        return policy.sample_batch(obs, 3, [torch.Generator().manual_seed(4) for _ in range(2)], **kw)

    a = draw(trained)
    assert torch.equal(draw(exported), a)
    assert torch.equal(draw(exported, use_ema=False), a)  # the refilled raw network is the average it samples with


def test_exported_world_model_keeps_every_weight(ckpts, tmp_path):
    out = tmp_path / "wm.ckpt"
    assert gpc("export", ckpts["wm"], "-o", out).exit_code == 0
    trained, exported = WorldModelModule.load_from_checkpoint(ckpts["wm"]), WorldModelModule.load_from_checkpoint(out)
    a, b = trained.state_dict(), exported.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert "raw_from_average" not in torch.load(out, weights_only=True)["gpc"]  # no averaged copy: nothing refilled


def test_a_half_export_rounds_the_weights_and_keeps_the_normaliser(ckpts, tmp_path):
    full, half = tmp_path / "full.ckpt", tmp_path / "half.ckpt"
    assert gpc("export", ckpts["policy"], "--out", full).exit_code == 0
    r = gpc("export", ckpts["policy"], "--out", half, "--half")
    assert r.exit_code == 0, r.output
    assert half.stat().st_size < 0.6 * full.stat().st_size
    a, b = torch.load(full, weights_only=True), torch.load(half, weights_only=True)
    assert b["gpc"]["half"] is True and "half" not in a["gpc"]
    for key, value in a["state_dict"].items():
        stored = b["state_dict"][key]
        if "normalizer." in key or not value.is_floating_point():
            assert stored.dtype == value.dtype and torch.equal(stored, value)  # the data's units, exact
        else:
            assert stored.dtype == torch.float16 and torch.equal(stored, value.half())
    loaded = PolicyModule.load_from_checkpoint(half)
    assert all(p.dtype == torch.float32 for p in loaded.parameters())  # plans in float32, with rounded weights
    weights = loaded.state_dict()
    assert weights["ema.model.unet.final.1.weight"].dtype == torch.float32
    assert torch.equal(weights["ema.model.unet.final.1.weight"], a["state_dict"]["ema.model.unet.final.1.weight"].half().float())
    obs = {k: torch.as_tensor(v) for k, v in histories([200000]).items()}
    trained, rounded = (policy.sample_batch(obs, 3, [torch.Generator().manual_seed(4)])
                        for policy in (PolicyModule.load_from_checkpoint(ckpts["policy"]), loaded))
    assert 0 < (rounded - trained).abs().max() < 0.5  # other numbers; the same actions to within half a pixel of 512


def test_export_refuses_to_replace_what_it_was_not_asked_to(ckpts, tmp_path):
    out = tmp_path / "kept.ckpt"
    out.write_bytes(b"the user's file")
    for flags in ((), ("--overwrite",)):  # a file gpc did not write is never replaced, --overwrite included
        r = gpc("export", ckpts["policy"], "--out", out, *flags)
        assert r.exit_code == 2 and f"{out}: exists and was not written by gpc" in r.output and "Traceback" not in r.output
        assert out.read_bytes() == b"the user's file"
    mine = tmp_path / "mine.ckpt"
    assert gpc("export", ckpts["policy"], "--out", mine).exit_code == 0
    r = gpc("export", ckpts["policy"], "--out", mine)
    assert r.exit_code == 2 and "already exists; choose another --out or pass --overwrite" in r.output
    assert gpc("export", ckpts["policy"], "--out", mine, "--overwrite").exit_code == 0  # gpc's own export: replaced
    assert PolicyModule.load_from_checkpoint(mine) is not None
    older = tmp_path / "older.ckpt"  # an export of a gpc that kept no record: its gpc record proves it
    shutil.copy(mine, older)
    assert gpc("export", ckpts["policy"], "--out", older, "--overwrite").exit_code == 0
    copy = tmp_path / "copy.ckpt"
    shutil.copy(ckpts["policy"], copy)
    r = gpc("export", copy, "--out", copy, "--overwrite")
    assert r.exit_code == 2 and "is the checkpoint being exported" in r.output
    assert copy.read_bytes() == Path(ckpts["policy"]).read_bytes()


def test_export_names_the_bad_input(tmp_path):
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    r = gpc("export", junk, "--out", tmp_path / "x.ckpt")
    assert r.exit_code == 2 and str(junk) in r.output and "unreadable or corrupt" in r.output
    r = gpc("export", tmp_path / "missing.ckpt", "--out", tmp_path / "x.ckpt")
    assert r.exit_code == 2 and "no such checkpoint file" in r.output
    r = gpc("export", junk, "--out", tmp_path / "x.pt")
    assert r.exit_code == 2 and "names a .ckpt file" in r.output
    assert not (tmp_path / "x.ckpt").exists()


def test_training_refuses_to_resume_an_export(ckpts, tmp_path):
    run_dir = tmp_path / "policy"
    (run_dir / "checkpoints").mkdir(parents=True)
    assert gpc("export", ckpts["policy"], "--out", run_dir / "checkpoints" / "last.ckpt").exit_code == 0
    config = policy_profile("tiny", "keypoints", LAYOUT).config
    try:
        train(PolicyModule, config, [Path(ckpts["dir"]) / "expert.zarr"],
              RunConfig(run_dir=run_dir, max_steps=30, batch_size=32, progress=False, accelerator="cpu", resume=True))
    except DataError as exc:
        assert "holds no optimiser state" in str(exc)
    else:
        raise AssertionError("resumed a checkpoint without optimiser state")


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_restore_vision_marks_exports_done_and_leaves_trainings_to_resume(ckpts, tmp_path):
    runs, art = tmp_path / "runs", tmp_path / "artifacts"
    art.mkdir()
    assert gpc("export", ckpts["policy"], "--out", art / "vpolicy.ckpt").exit_code == 0
    shutil.copy(ckpts["wm"], art / "wm-visual-phase1.resume.ckpt")  # a training stopped half-way
    (runs / "reward" / "checkpoints").mkdir(parents=True)
    (runs / "reward" / "checkpoints" / "last.ckpt").write_bytes(b"the user's own run")
    shutil.copy(art / "vpolicy.ckpt", art / "reward.ckpt")  # stands for an exported reward: never copied over theirs
    assert gpc("export", ckpts["wm"], "--out", art / "wm-visual-onpolicy.ckpt").exit_code == 0  # the on-policy teacher
    for store in ("expert", "explore"):
        (runs / f"{store}.done").touch()
    venv = Path(sys.executable).parent.parent
    make = ["make", "-s", f"VENV={venv}", "PROFILE=smoke", f"RUN_DIR={runs}", f"ARTIFACTS={art}"]
    done = subprocess.run([*make, "restore-vision"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (runs / "vpolicy" / "checkpoints" / "last.ckpt").read_bytes() == (art / "vpolicy.ckpt").read_bytes()
    assert (runs / "wm-visual-phase1" / "checkpoints" / "last.ckpt").read_bytes() == Path(ckpts["wm"]).read_bytes()
    assert (runs / "reward" / "checkpoints" / "last.ckpt").read_bytes() == b"the user's own run"
    assert (runs / "vpolicy.done").exists() and not (runs / "wm-visual-phase1.done").exists()
    assert not (runs / "reward.done").exists()
    # a kept on-policy teacher is a finished stage that stands for its recording (whose store is not kept)
    recorded, tuned = runs / "wm-visual-opt-episodes.done", runs / "wm-visual-onpolicy.done"
    stamps = [(runs / "vpolicy.done").stat().st_mtime_ns, recorded.stat().st_mtime_ns, tuned.stat().st_mtime_ns]
    assert stamps == sorted(stamps)  # after the stages it was recorded with, before the teacher: make records nothing
    assert not (runs / "wm-visual-opt-episodes.zarr").exists()
    # the restored policy stage is up to date (make -q: nothing to run); the half-way training is not
    assert subprocess.run([*make, "-q", str(runs / "vpolicy.done")], cwd=ROOT).returncode == 0
    assert subprocess.run([*make, "-q", str(runs / "wm-visual-phase1.done")], cwd=ROOT).returncode == 1


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_keep_vision_then_restore_vision_carries_the_stages_to_a_new_machine(ckpts, tmp_path):
    runs, art, venv = tmp_path / "runs", tmp_path / "artifacts", Path(sys.executable).parent.parent
    for name, src in (("vpolicy", ckpts["policy"]), ("wm-visual-phase1", ckpts["wm"])):
        (runs / name / "checkpoints").mkdir(parents=True)
        shutil.copy(src, runs / name / "checkpoints" / "last.ckpt")
    (runs / "vpolicy.done").touch()  # the policy finished; the world model's training is half-way
    done, stopped = tmp_path / "results-vision" / "bc", tmp_path / "results-vision" / "vrank-K3"
    (done / ".groups").mkdir(parents=True)
    (stopped / ".groups").mkdir(parents=True)
    for path in (done / "summary.json", done / ".groups" / "0.json", stopped / ".groups" / "0.json", done / "a.mp4"):
        path.write_text("{}")
    make = ["make", "-s", f"VENV={venv}", "PROFILE=smoke", f"RESULTS={tmp_path / 'results'}", f"RUN_DIR={runs}",
            f"ARTIFACTS={art}"]
    small = subprocess.run([*make, "keep-vision", "KEEP_RESUME_MB=0"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert small.returncode == 0 and "not kept" in small.stdout and not (art / "wm-visual-phase1.resume.ckpt").exists()
    kept = subprocess.run([*make, "keep-vision"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert kept.returncode == 0, kept.stderr
    assert (runs / "vpolicy" / "checkpoints" / "trained.ckpt").read_bytes() == Path(ckpts["policy"]).read_bytes()
    assert (runs / "vpolicy" / "checkpoints" / "last.ckpt").read_bytes() == (art / "vpolicy.ckpt").read_bytes()
    assert torch.load(art / "vpolicy.ckpt", weights_only=True)["gpc"]["half"] is True  # stored in float16
    assert (art / "wm-visual-phase1.resume.ckpt").read_bytes() == Path(ckpts["wm"]).read_bytes()
    kept_results = sorted(str(p.relative_to(art)) for p in art.rglob("*.json") if p.name != ".gpc-files.json")
    assert kept_results == ["results/results-vision/bc/.groups/0.json", "results/results-vision/bc/summary.json",
                            "results/results-vision/vrank-K3/.groups/0.json"]  # the videos stay behind
    stamp = (art / "vpolicy.ckpt").stat().st_mtime_ns
    assert subprocess.run([*make, "keep-vision"], cwd=ROOT, capture_output=True, timeout=300).returncode == 0
    assert (art / "vpolicy.ckpt").stat().st_mtime_ns == stamp  # already kept: not exported again
    onpolicy = tmp_path / "results-vision-onpolicy" / "vopt-M2"  # the default model's rows (VWM_PLAN=onpolicy), beside the shared BC
    (onpolicy / ".groups").mkdir(parents=True)
    (onpolicy / ".groups" / "0.json").write_text("{}")
    assert subprocess.run([*make, "keep-vision"], cwd=ROOT, capture_output=True, timeout=300).returncode == 0
    assert (art / "results" / "results-vision-onpolicy" / "vopt-M2" / ".groups" / "0.json").exists()
    assert (art / "results" / "results-vision" / "bc" / "summary.json").exists()
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    shutil.rmtree(tmp_path / "results-vision")
    for store in ("expert", "explore"):
        (fresh / f"{store}.done").touch()
    restored = subprocess.run([*make[:-2], f"RUN_DIR={fresh}", f"ARTIFACTS={art}", "restore-vision"], cwd=ROOT,
                              capture_output=True, text=True, timeout=300)
    assert restored.returncode == 0, restored.stderr
    for name in ("vpolicy", "wm-visual-phase1"):
        assert (fresh / name / "checkpoints" / "last.ckpt").read_bytes() == (runs / name / "checkpoints" / "last.ckpt").read_bytes()
    assert (fresh / "vpolicy.done").exists() and not (fresh / "wm-visual-phase1.done").exists()
    assert (stopped / ".groups" / "0.json").exists() and not (stopped / "summary.json").exists()
    assert (done / "summary.json").stat().st_mtime_ns >= (fresh / "vpolicy.done").stat().st_mtime_ns  # up to date for make
