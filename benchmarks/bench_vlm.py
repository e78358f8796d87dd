"""What one VLM-reward decision costs, measured against the scripted loopback server.

Each decision renders the K predicted final Push-T states, tiles and PNG-encodes them and
sends one chat-completions request. The server answers at once, so the latency is the
client's own overhead (render, tile, encode, HTTP on loopback); a real model adds its
inference time on top. Token counts are the server's estimates (Qwen2.5-VL's image-token
rule, ~4 characters per text token), not a tokenizer's.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import publish
from benchmarks.vlm_server import Reply, ScriptedChatServer
from gpc.models.rewards.vlm import VLMConfig, VLMReward
from gpc.tasks.pusht import render_state


def _futures(k: int, rng: np.random.Generator) -> torch.Tensor:
    """``(k, 16, 5)`` Push-T states, different every call so no decision is a cache hit."""
    lo, hi = np.array([50, 50, 100, 100, -np.pi]), np.array([450, 450, 400, 400, np.pi])
    return torch.from_numpy(rng.uniform(lo, hi, (k, 16, 5)))


def decision_row(k: int, decisions: int) -> list[str]:
    rng = np.random.default_rng(k)
    with ScriptedChatServer([Reply("1")]) as server:
        vlm = VLMReward(VLMConfig(base_url=server.base_url, model="bench-vl", timeout_s=30.0, max_retries=0),
                        render=lambda s, g: render_state(s, size=96), task_description="push the grey T onto the green T")
        vlm(_futures(k, rng))  # warm-up: imports the client and opens the connection
        warm = vlm.stats
        wall, query = [], []
        for _ in range(decisions):
            futures = _futures(k, rng)
            before, t0 = vlm.stats["seconds"], time.perf_counter()
            vlm(futures)
            wall.append(time.perf_counter() - t0)
            query.append(vlm.stats["seconds"] - before)
        stats = vlm.stats
        request = server.requests[-1]
    n = stats["decisions"] - warm["decisions"]
    assert stats["fell_back"] == 0 and stats["cache_hits"] == 0, stats
    height, width = request.images()[0].shape[:2]
    per = lambda key: (stats[key] - warm[key]) / n  # noqa: E731
    return [str(k), f"{width}x{height}", f"{request.size / 1024:,.0f} KiB", f"{per('queries'):.0f}",
            f"{per('prompt_tokens'):,.0f}", f"{per('completion_tokens'):.0f}",
            f"{statistics.median(wall) * 1e3:,.1f} ms", f"{statistics.median(query) * 1e3:,.1f} ms"]


def run(doc: Path | None, decisions: int = 15) -> None:
    rows = [decision_row(k, decisions) for k in (4, 16, 100)]
    header = ["K", "image", "request", "queries/decision", "prompt tokens", "completion tokens",
              "decision (median)", "of which HTTP query (median)"]
    publish(f"VLM reward per decision, loopback server, {decisions} decisions each", "vlm", header, rows, doc, key=1)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--decisions", type=int, default=15)
    args = parser.parse_args()
    run(args.doc, args.decisions)
