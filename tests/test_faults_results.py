"""Results: comparisons refuse what is not comparable, and damaged or foreign results are named, never replaced."""

from __future__ import annotations

import json
import shutil
import signal
from pathlib import Path

import pytest
from faults import digest, finish, gpc, inline, one_line, spawn, wait_deferring, wide_store

pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------- comparisons refuse what is not comparable
def test_compare_refuses_runs_of_other_settings_and_names_damaged_files(tiny_pusht, tmp_path):
    base = ["eval", str(tiny_pusht["policy"]), "--seeds", "100000:100002", "--batch", "2"]
    assert inline(*base, "--max-steps", "20", "--out", str(tmp_path / "bc"))[0] == 0
    assert inline(*base, "--max-steps", "30", "--out", str(tmp_path / "bc30"))[0] == 0
    out = str(tmp_path / "t.md")
    one_line(gpc("compare", str(tmp_path / "bc30"), "--baseline", str(tmp_path / "bc"), "--out", out), 2,
             "--max-steps 30 differs from the baseline's 20")
    (tmp_path / "bc30" / "summary.json").write_text('{"config": ')
    one_line(gpc("compare", str(tmp_path / "bc30"), "--baseline", str(tmp_path / "bc"), "--out", out), 2,
             str(tmp_path / "bc30" / "summary.json"), "not valid JSON")
    assert not Path(out).exists()


def test_results_of_another_kind_are_never_replaced(tiny_pusht, tmp_path):
    res = tmp_path / "res"
    assert inline("eval", str(tiny_pusht["policy"]), "--seeds", "100000:100002", "--max-steps", "5", "--out", str(res))[0] == 0
    before = digest(res)
    one_line(inline("compare", str(res), "--baseline", str(res), "--out", str(res / "summary.md")), 2,
             "not a comparison gpc wrote")
    one_line(inline("eval", str(tiny_pusht["policy"]), "--seeds", "100000:100002", "--max-steps", "5", "--sampling-seeds", "0,1",
                    "--out", str(res)), 2, str(res), "already holds results")
    one_line(inline("eval", str(tiny_pusht["policy"]), "--sampling-seeds", "0,0", "--out", str(tmp_path / "twice")), 2,
             "--sampling-seeds: 0 given twice")
    assert digest(res) == before and not (res / "sampling-seed-0").exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    one_line(inline("data", "video", str(tiny_pusht["store"]), "--out", str(notes)), 2, str(notes), ".mp4 file")
    one_line(inline("check-sim", "--data", str(tiny_pusht["store"]), "--out", str(tmp_path)), 2, str(tmp_path), "is a folder")
    assert notes.read_text() == "mine"


@pytest.mark.parametrize("case", ["summary list", "episodes not objects", "score a string", "no ceiling seed",
                                  "zarray empty", "precision 64", "lr nan", "lr inf", "steps", "aggregate"])
def test_damaged_results_and_bad_values_are_one_line(tiny_pusht, tmp_path, case):
    policy, wm = str(tiny_pusht["policy"]), str(tiny_pusht["wm"])
    plan = ["eval", policy, "--planner", "rank", "--world-model", wm, "--seeds", "100000", "--out", str(tmp_path / "r")]
    train_args = ["train", "policy", "--dataset", str(tiny_pusht["store"]), "--out", str(tmp_path / "run"), "--profile", "tiny",
                  "--max-steps", "2", "--accelerator", "cpu", "--no-progress"]
    if case in ("summary list", "episodes not objects", "score a string", "no ceiling seed"):
        res = tmp_path / "r"
        assert inline("eval", policy, "--seeds", "100000:100002", "--max-steps", "5", "--out", str(res))[0] == 0
        cmd = ["compare", str(res), "--baseline", str(res), "--out", str(tmp_path / "c.md")]
        if case == "summary list":
            (res / "summary.json").write_text("[]")
            one_line(inline("eval", policy, "--seeds", "100000:100002", "--out", str(res)), 2, str(res / "summary.json"),
                     "was not written by gpc")
            return
        if case == "no ceiling seed":
            top = tmp_path / "top"
            assert inline("eval", policy, "--seeds", "100000", "--max-steps", "5", "--out", str(top))[0] == 0
            one_line(inline(*cmd, "--ceiling", str(top)), 2, "--ceiling lacks seed(s) [100001]")
            return
        rows = json.loads((res / "episodes.json").read_text())
        (res / "episodes.json").write_text(json.dumps([1] if case == "episodes not objects" else
                                                      [{**r, "score": "high"} for r in rows]))
        one_line(inline(*cmd), 2, str(res / "episodes.json"))
    elif case == "zarray empty":
        copy = tmp_path / "copy.zarr"
        shutil.copytree(tiny_pusht["store"], copy)
        (copy / "meta" / "episode_ends" / ".zarray").write_text("{}")
        one_line(inline("data", "info", str(copy)), 2, str(copy / "meta" / "episode_ends" / ".zarray"), "damaged metadata")
    elif case == "precision 64":
        one_line(inline(*train_args, "--precision", "64-true"), 2, "--precision 64-true")
        assert not (tmp_path / "run").exists()
    elif case.startswith("lr"):
        one_line(inline(*plan, "--lr", case.split()[1]), 2, f"--lr {case.split()[1]}")
        assert not (tmp_path / "r").exists()
    elif case == "steps":
        one_line(inline("eval", policy, "--steps", "100000", "--out", str(tmp_path / "r")), 2, "--steps 100000")
    else:
        one_line(inline(*plan, "--reward-aggregate", "foo"), 2, "--reward-aggregate 'foo'")


def test_the_rest_of_the_reported_cases_are_one_line_each(tiny_pusht, tmp_path):
    """Ctrl-C of eval-expert; --lr names only --lr; data info of a store laid out otherwise; a summary missing a key."""
    proc = spawn("eval-expert", "--seeds", "100000:100100")
    wait_deferring(proc)
    one_line(finish(proc, signal.SIGINT), 130, "stopped by SIGINT", "episodes were scored", alone=False)
    lr = one_line(inline("eval", str(tiny_pusht["policy"]), "--planner", "rank", "--world-model", str(tiny_pusht["wm"]), "--lr", "-5",
                         "--out", str(tmp_path / "lr")), 2, "--lr -5")
    assert "temperature" not in lr and "init_std" not in lr
    info = gpc("data", "info", str(wide_store(tmp_path / "w.zarr")))
    assert info.returncode == 0 and "no task figures" in info.stdout and "Traceback" not in info.stderr
    assert inline("eval", str(tiny_pusht["policy"]), "--seeds", "100000", "--max-steps", "5", "--out", str(tmp_path / "bc"))[0] == 0
    summary = json.loads((tmp_path / "bc" / "summary.json").read_text())
    del summary["decision_latency_s"]
    (tmp_path / "bc" / "summary.json").write_text(json.dumps(summary))
    one_line(gpc("compare", str(tmp_path / "bc"), "--baseline", str(tmp_path / "bc"), "--out", str(tmp_path / "t.md")), 2,
             str(tmp_path / "bc" / "summary.json"), "'decision_latency_s'")
