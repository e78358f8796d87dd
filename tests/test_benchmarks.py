"""`make bench` keeps working: every benchmark runs at a tiny size and writes its rows to a doc, replacing a
setting's earlier row (the doc holds the latest figures, not a growing log). Timings are not asserted."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import bench_planners, bench_policy, bench_tasks, bench_vlm, bench_world_model, common

pytestmark = pytest.mark.usefixtures("one_thread")


def table(doc: Path, name: str) -> list[str]:
    text = doc.read_text()
    begin, end = f"<!-- bench:{name}:begin -->", f"<!-- bench:{name}:end -->"
    return text[text.index(begin) + len(begin) : text.index(end)].strip().splitlines()[2:]


def test_rows_replace_the_same_settings_latest_figures(tmp_path):
    doc = tmp_path / "bench.md"
    common.write_rows(doc, "x", ["work", "setting", "ms"], [["a", "1", "5"], ["b", "1", "6"]], key=2)
    common.write_rows(doc, "x", ["work", "setting", "ms"], [["a", "1", "4"], ["c", "2", "7"]], key=2)
    rows = table(doc, "x")
    assert len(rows) == 3 and [r.split("|")[3].strip() for r in rows] == ["b", "a", "c"]
    assert rows[1].rstrip(" |").endswith("4")  # a's latest figure
    lines = doc.read_text().splitlines()  # a row measured on another kind of machine is another row
    doc.write_text("\n".join(line.replace(common.machine(), "riscv64 RVV, 64 cores") if "| b |" in line else line
                             for line in lines))
    common.write_rows(doc, "x", ["work", "setting", "ms"], [["b", "1", "3"]], key=2)
    rows = table(doc, "x")
    assert len(rows) == 4 and sum("| b |" in r for r in rows) == 2 and "riscv64 RVV" in rows[0]


@pytest.mark.extended  # make test-extended (half a minute); make test checks the tables' rows above and below
def test_every_benchmark_runs_small_and_writes_its_table(tmp_path):
    doc = tmp_path / "bench.md"
    common.publish("policy", "policy", ["work", "setting", "throughput", "latency (median)", "target"],
                   bench_policy.train_rows(["tiny"], "keypoints"), doc)
    bench_world_model.run(doc, kinds=("state",), ks=(1,))
    bench_planners.run(doc, settings=[s for s in bench_planners.SETTINGS if s[0] in ("rank K=10", "cem 100x5", "gt-sim K=100")],
                       samplers=(2,), profile="tiny")
    bench_vlm.run(doc, decisions=1)
    bench_tasks.run(doc, tasks=("draw",))
    assert [r.split("|")[4].strip() for r in table(doc, "tasks")][:2] == ["state step + reward", "render 96x96 (env.frame)"]
    assert len(table(doc, "policy")) == 1 and len(table(doc, "world_model")) == 1
    assert len(table(doc, "planners")) == 3 and len(table(doc, "vlm")) == 3


def test_table_cost_counts_decisions_from_the_episodes_kept():
    from benchmarks.table_cost import cost

    folder = Path(__file__).parents[1] / "artifacts/pusht-cpu/results/pusht-cpu-vision-onpolicy/vrank-K100"
    own, paper = cost(folder), cost(folder, seconds=11.745)
    # 100 episodes of at most 300 steps, 8 actions a decision, ending at success: 31.3 decisions each
    assert (own["episodes"], own["decisions"]) == (100, 3132) and paper["decisions"] == 3132
    assert paper["hours"] == pytest.approx(3132 * 11.745 / 3600) and own["s_per_decision"] == pytest.approx(4.9686, abs=1e-3)
