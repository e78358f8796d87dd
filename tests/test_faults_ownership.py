"""Faults of the write rule (issue 43 item 1): gpc never replaces or deletes a file it did not write.

Each case puts a file of the user's where a command writes (or inside a store gpc wrote), runs the real command, and
checks exit 2, one line naming that file, and every byte still there; then that a file gpc wrote itself is replaced
by a re-run, and that an older gpc's outputs (no ownership record) are still recognised by their content.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from faults import digest, gpc, inline, one_line

from gpc.harness.ownership import RECORD, is_ours

MINE = "the user's own notes\n"


def _mine(*paths: Path) -> None:
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(MINE)


def test_collect_overwrite_refuses_a_gpc_store_holding_the_users_files(tiny_pusht, tmp_path):
    store = tmp_path / "a.zarr"
    shutil.copytree(tiny_pusht["store"], store)
    _mine(store / "NOTES.md", store / "data" / "state" / "why.txt")
    before = digest(store)
    one_line(inline("collect", "--out", str(store), "--episodes", "2", "--no-images", "--max-steps", "20", "--overwrite"), 2,
             str(store), "NOTES.md", "data/state/why.txt", "move them out of the store first")
    assert digest(store) == before and not (tmp_path / ".a.zarr.new").exists()
    (store / "NOTES.md").unlink()
    (store / "data" / "state" / "why.txt").unlink()
    assert inline("collect", "--out", str(store), "--episodes", "2", "--no-images", "--max-steps", "20", "--overwrite")[0] == 0


@pytest.mark.parametrize("flags", [(), ("--overwrite",), ("--resume",), ("--resume", "--overwrite")])
def test_eval_never_replaces_the_users_results_files(tiny_pusht, tmp_path, flags):
    out = tmp_path / "r"
    _mine(out / "summary.md", out / "episodes.json")
    before = digest(out)
    one_line(inline("eval", str(tiny_pusht["policy"]), "--seeds", "100000", "--max-steps", "5", "--out", str(out), *flags), 2,
             str(out / "episodes.json"), "was not written by gpc")
    assert digest(out) == before


def test_eval_replaces_its_own_results_but_not_a_file_edited_since(tiny_pusht, tmp_path):
    out = tmp_path / "r"
    run = ["eval", str(tiny_pusht["policy"]), "--seeds", "100000", "--max-steps", "5", "--out", str(out)]
    assert inline(*run)[0] == 0
    assert all(is_ours(out / name) for name in ("episodes.json", "summary.json", "summary.md"))
    assert inline(*run[:-4], "--max-steps", "6", "--out", str(out), "--overwrite")[0] == 0  # another run: replaced
    assert json.loads((out / "summary.json").read_text())["config"]["max_steps"] == 6
    (out / "summary.md").write_text((out / "summary.md").read_text() + "my remark\n")  # now partly the user's
    before = digest(out)
    one_line(inline(*run, "--overwrite"), 2, str(out / "summary.md"), "was not written by gpc")
    assert digest(out) == before


def test_an_older_gpcs_results_are_still_gpcs(tiny_pusht, tmp_path):
    """Results written before gpc kept its record are known by their run record, and replaced as before."""
    out = tmp_path / "r"
    run = ["eval", str(tiny_pusht["policy"]), "--seeds", "100000", "--max-steps", "5", "--out", str(out)]
    assert inline(*run)[0] == 0
    (out / RECORD).unlink()
    assert not is_ours(out / "summary.md")
    assert inline(*run[:-4], "--max-steps", "6", "--out", str(out), "--overwrite")[0] == 0
    assert is_ours(out / "summary.md")


def test_report_commands_never_replace_the_users_files(tiny_pusht, tmp_path):
    notes = tmp_path / "mine.md"
    ascent = ["eval", "ascent", str(tiny_pusht["policy"]), "--planner", "opt", "-M", "1", "--world-model", str(tiny_pusht["wm"]),
              "--seeds", "200000", "--max-steps", "8"]
    _mine(notes)
    one_line(inline(*ascent, "--out", str(notes)), 2, str(notes), "was not written by gpc")
    _mine(tmp_path / "beside.json")  # the JSON the report writes beside its .md
    one_line(inline(*ascent, "--out", str(tmp_path / "beside.md")), 2, str(tmp_path / "beside.json"))
    check = tmp_path / "mine.json"
    _mine(check)
    one_line(inline("check-sim", "--data", str(tiny_pusht["store"]), "--episodes", "1", "--out", str(check)), 2, str(check))
    video = tmp_path / "holiday.mp4"
    _mine(video)
    one_line(inline("data", "video", str(tiny_pusht["store"]), "--out", str(video)), 2, str(video), "was not written by gpc")
    evals = tmp_path / "evals"
    _mine(evals / "world_model_eval.md", evals / "expert.md", evals / "reward_eval.json")
    one_line(inline("eval", "world-model", str(tiny_pusht["wm"]), "--dataset", str(tiny_pusht["store"]), "--out", str(evals)), 2,
             str(evals / "world_model_eval.md"))
    one_line(inline("eval-expert", "--seeds", "100000", "--out", str(evals)), 2, str(evals / "expert.md"))
    for path in (notes, tmp_path / "beside.json", check, video, evals / "world_model_eval.md", evals / "expert.md"):
        assert path.read_text() == MINE
    assert not (tmp_path / "beside.md").exists() and not (evals / "world_model_eval.json").exists()


def test_a_rerun_replaces_what_gpc_wrote(tiny_pusht, tmp_path):
    video, check = tmp_path / "ep.mp4", tmp_path / "check.json"
    for _ in range(2):
        assert inline("data", "video", str(tiny_pusht["store"]), "--out", str(video))[0] == 0
        assert inline("check-sim", "--data", str(tiny_pusht["store"]), "--episodes", "1", "--out", str(check))[0] == 0
    assert is_ours(video) and is_ours(check)
    record = json.loads((tmp_path / RECORD).read_text())["files"]
    assert record["ep.mp4"]["by"].startswith("gpc") and "pending" not in record["ep.mp4"]


def test_compare_never_replaces_the_users_plot(tiny_pusht, tmp_path):
    res = tmp_path / "bc"
    assert inline("eval", str(tiny_pusht["policy"]), "--seeds", "100000:100002", "--max-steps", "5", "--out", str(res))[0] == 0
    out = tmp_path / "cmp.md"
    _mine(out.with_suffix(".png"))
    one_line(inline("compare", str(res), "--baseline", str(res), "--out", str(out)), 2, str(out.with_suffix(".png")))
    assert out.with_suffix(".png").read_text() == MINE and not out.exists()
    out.with_suffix(".png").unlink()
    for _ in range(2):  # gpc's own comparison is replaced by a re-run
        assert inline("compare", str(res), "--baseline", str(res), "--out", str(out))[0] == 0


def test_a_replacement_killed_between_rename_and_record_is_still_gpcs(tmp_path):
    """The record holds the new content as pending before the rename: either file is gpc's after a crash."""
    from gpc.harness.ownership import _record, write_bytes

    path = tmp_path / "r.json"
    write_bytes(path, b"old")
    with _record(tmp_path) as files:  # as write_bytes leaves it just before its rename
        files["r.json"]["pending"] = "0" * 64
    assert is_ours(path)
    path.write_bytes(b"mine")
    assert not is_ours(path)
    with pytest.raises(ValueError, match="was not written by gpc"):
        write_bytes(path, b"new")
    assert path.read_bytes() == b"mine"


def test_a_stopped_lerobot_conversion_never_removes_a_folder_of_the_users(tiny_pusht, tmp_path):
    mine = tmp_path / ".out.partial"  # the name older gpc staged into, and removed when it found it
    _mine(mine / "keep.txt")
    done = gpc("data", "export", str(tiny_pusht["store"]), "--out", str(tmp_path / "out"), "--no-images")
    assert done.returncode == 0, done.stderr
    assert (mine / "keep.txt").read_text() == MINE
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".lock") == [".out.partial", "out"]  # no staging left
