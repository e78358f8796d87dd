"""The robot side of `gpc serve`, with the simulator as the robot: episodes at the control rate through ``gpc.client``.

Start a server (any checkpoint and planner `gpc eval` takes), then run this in another process (or on another computer):

    gpc serve artifacts/pusht-cpu/vpolicy.ckpt --port 8765 &
    python examples/robot_loop.py --url ws://127.0.0.1:8765 --seeds 100000:100003 --mode async --video robot.mp4

``--mode sync`` plans a decision at a time and executes its head (the robot stands still while planning; the scores
equal `gpc eval --batch 1` on the same seeds); ``--mode async`` keeps executing the current chunk at the task's rate
(10 Hz for Push-T) while the next one is planned (``gpc.client.AsyncChunks``). A real robot replaces
``gpc.serving.robot.SimRobot`` (reset, observe, step) by its driver and camera; the rest stays.
Prints one JSON line per episode and a summary: score, round trips, planning seconds, idle seconds per decision,
payload bytes and the serialisation time of one request.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from gpc.client import PolicyClient
from gpc.serving import wire
from gpc.serving.robot import SimRobot, async_episode, sync_episode


def seeds_of(text: str) -> list[int]:
    if ":" in text:
        start, stop = text.split(":")
        return list(range(int(start), int(stop)))
    return [int(s) for s in text.split(",")]


def payload(client: PolicyClient) -> dict[str, float]:
    """A request's and a reply's size, and their serialisation (pack + unpack) time, without the network."""
    obs = client.history(SimRobot(client).reset(0)).arrays()
    request = {"type": "act", "id": 1, "episode": 0, "decision": 0, "obs": obs}
    m = client.metadata
    reply = {"type": "action", "id": 1, "episode": 0, "decision": 0, "action_steps": m["action_steps"], "planning_s": 0.0,
             "chunk": np.zeros((m["chunk_length"], m["action"]["dim"]), np.float32)}
    out = {}
    for name, message in (("request", request), ("reply", reply)):
        n = 200
        t0 = time.perf_counter()
        for _ in range(n):
            raw = wire.pack(message)
            wire.unpack(raw)
        out[f"{name}_bytes"], out[f"{name}_pack_unpack_ms"] = len(raw), (time.perf_counter() - t0) / n * 1e3
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="ws://127.0.0.1:8765")
    parser.add_argument("--token", default=None, help="The server's --token (default: $GPC_TOKEN).")
    parser.add_argument("--seeds", default="100000:100003")
    parser.add_argument("--mode", choices=("sync", "async"), default="async")
    parser.add_argument("--max-steps", type=int, default=None, help="Steps per episode at most (default: the task's).")
    parser.add_argument("--fps", type=float, default=None, help="Control rate of --mode async (default: the task's).")
    parser.add_argument("--video", type=Path, default=None, help="MP4 of the episodes, one after the other.")
    parser.add_argument("--json", type=Path, default=None, help="Write the episodes and the summary here.")
    args = parser.parse_args()

    import os

    frames: list[np.ndarray] = []
    keep = frames.append if args.video else None
    with PolicyClient(args.url, token=args.token or os.environ.get("GPC_TOKEN")) as client:
        meta = client.metadata
        print(f"# {meta['controller']} on {meta['task']}: {meta['chunk_length']} actions per chunk, "
              f"{meta['action_steps']} executed per decision, {meta['fps']} Hz; mode {args.mode}")
        rows = []
        for seed in seeds_of(args.seeds):
            if args.mode == "sync":
                row = sync_episode(client, seed, args.max_steps, keep)
            else:
                row = async_episode(client, seed, args.max_steps, args.fps, frames=keep)
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if not isinstance(v, list)}
                             | {"decisions": len(row["planning_s"]),
                                "idle_s_per_decision": statistics.fmean(row.get("idle_s", [0.0])),
                                "round_trip_s_p50": statistics.median(row["round_trip_s"]),
                                "planning_s_p50": statistics.median(row["planning_s"])}))
        trips = [t for r in rows for t in r["round_trip_s"]]
        plans = [p for r in rows for p in r["planning_s"]]
        summary = {"controller": meta["controller"], "mode": args.mode, "episodes": len(rows),
                   "mean_score": statistics.fmean(r["score"] for r in rows),
                   "success_rate": statistics.fmean(float(r["success"]) for r in rows),
                   "decisions": len(trips), "round_trip_s_p50": statistics.median(trips),
                   "planning_s_p50": statistics.median(plans),
                   "wire_s_p50": statistics.median(t - p for t, p in zip(trips, plans)),
                   **payload(client)}
        if args.mode == "async":
            idle = [i for r in rows for i in r["idle_s"][1:]]  # the first decision of an episode is synchronous
            summary |= {"idle_s_per_decision": statistics.fmean(idle) if idle else 0.0,
                        "skipped_per_decision": statistics.fmean(s for r in rows for s in r["skipped"][1:])}
    print(json.dumps(summary))
    if args.json:
        args.json.write_text(json.dumps({"metadata": meta, "summary": summary, "episodes": rows}, indent=1))
    if args.video:
        from gpc.harness.video import write_mp4

        write_mp4(frames, args.video, fps=int(meta["fps"]))
        print(f"wrote {args.video} ({len(frames)} frames)")


if __name__ == "__main__":
    main()
