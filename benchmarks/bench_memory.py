"""A visual rollout with glibc's defaults against freed memory kept (``gpc.harness.memory``), each in its own process.

glibc maps every block above 32 MB on its own and unmaps it when freed, so each large activation of a rollout faults its
pages in again; gpc's processes keep freed memory instead. The ``cpu`` profile's visual model (untrained: the time does
not depend on the weights), float32, one thread, N candidates from one history.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from benchmarks.common import publish

ROLLOUT = """
import json, resource, statistics, sys, time
import torch
from gpc.harness.memory import keep_freed_memory
if sys.argv[1] == "kept":
    keep_freed_memory()
from benchmarks.bench_world_model import _inputs, _model
torch.set_num_threads(1)
model = _model("image", None, "cpu")
model.set_rollout_precision("32-true")
history, actions = _inputs(model, "image", int(sys.argv[2]))
times = []
with torch.no_grad():
    for _ in range(int(sys.argv[3]) + 1):  # the first is a warm-up
        t0 = time.perf_counter()
        model.rollout(history, actions)
        times.append(time.perf_counter() - t0)
use = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"s": statistics.median(times[1:]), "faults": use.ru_minflt, "sys": use.ru_stime, "peak_gb": use.ru_maxrss / 1e6}))
"""


def _measure(mode: str, k: int, repeat: int) -> dict:
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", ROLLOUT, mode, str(k), str(repeat)], cwd=root, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(doc: Path | None, ks: tuple[int, ...] = (100, 1000), repeat: int = 2) -> None:
    rows = []
    for k in ks:
        default, kept = _measure("default", k, repeat), _measure("kept", k, repeat)
        rows.append([f"{k} candidates", f"{default['s']:.2f} s ({default['faults'] / 1e6:.1f} M faults, {default['peak_gb']:.2f} GB)",
                     f"{kept['s']:.2f} s ({kept['faults'] / 1e6:.1f} M faults, {kept['peak_gb']:.2f} GB)",
                     f"{default['s'] / kept['s']:.1f}x"])
    header = ["rollout", "glibc defaults (page faults, peak)", "freed memory kept", "speed-up"]
    publish("Visual rollout, float32, one thread: glibc defaults against freed memory kept", "memory", header, rows, doc, key=1)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    run(args.doc, repeat=args.repeat)
