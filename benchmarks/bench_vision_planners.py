"""Seconds per decision of the vision planners for one observation history, with the levers that cut it.

Targets on 2 cores (issue 19): GPC-RANK K=100 <= 2 s, GPC-OPT M=25 <= 3 s, GPC-RANK+OPT 10x25
<= 5 s per decision (the paper's GPU: 11.7, 39.1, 374 s). The image policy proposes (DDIM-10),
the visual world model (``cpu`` profile: 48 px, frameskip 4) predicts, the learned image
reward reads the final predicted frame. Levers timed: Euler steps per predicted frame (3: the
trained sampler; 1: a ``--distill`` student, the same network), bf16 rollouts, channels-last
memory. Latency does not depend on the weights, so untrained networks of the profiles'
shapes are timed unless checkpoints are given; the scores of each lever come from ``gpc eval``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_policy import _policy
from benchmarks.bench_world_model import _model, _reward
from benchmarks.common import publish, time_decisions
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.planner import model_planner
from gpc.models.policy.module import PolicyModule
from gpc.tasks.pusht import LAYOUT, observe
from gpc.tasks.pusht.env import PushTEnv

SETTINGS = [  # (label, planner config fields, target)
    ("rank K=50", dict(kind="rank", num_proposals=50), ""),
    ("rank K=100", dict(kind="rank", num_proposals=100), "<= 2 s"),
    ("opt M=25", dict(kind="opt", num_proposals=1, opt_steps=25), "<= 3 s"),
    ("rank-opt 10x25", dict(kind="rank-opt", num_proposals=10, opt_steps=25), "<= 5 s"),
]
LEVERS = [  # (label, Euler steps per frame, bf16, channels-last)
    ("3 Euler steps, bf16", 3, True, False),
    ("1 Euler step (distilled), bf16", 1, True, False),
    ("1 Euler step (distilled), fp32", 1, False, False),
    ("1 Euler step (distilled), bf16, channels-last", 1, True, True),
]


def _with_lever(model: torch.nn.Module, steps: int, bf16: bool, channels_last: bool) -> None:
    dyn = model.dynamics  # type: ignore[attr-defined]
    dyn.use_sampler(dataclasses.replace(dyn.config.sampler, steps=steps))
    dyn.config = dataclasses.replace(dyn.config, bf16=bf16)
    model.to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


def run(doc: Path | None, policy_ckpt: str | None = None, wm_ckpt: str | None = None, reward_ckpt: str | None = None,
        settings: list = SETTINGS, levers: list = LEVERS, repeat: int = 3) -> None:
    torch.manual_seed(0)
    policy = PolicyModule.load_from_checkpoint(policy_ckpt) if policy_ckpt else _policy("cpu", "image")
    model, reward = _model("image", wm_ckpt, "cpu"), _reward("image", reward_ckpt, "cpu")
    env = PushTEnv()
    env.reset(seed=100000)
    o = observe(env, images=True, sim=False)
    n = max(policy.config.n_obs_steps, model.n_obs_steps)
    obs = {k: np.stack([v] * n)[None] for k, v in o.items()}
    box = {"action_low": LAYOUT.action.low, "action_high": LAYOUT.action.high}
    rows = []
    for lever, steps, bf16, channels_last in levers:
        _with_lever(model, steps, bf16, channels_last)
        for label, fields, target in settings:
            planner = model_planner(PlannerConfig(**fields, **box), model, reward, policy, SamplingConfig("ddim", 10))
            t, share = time_decisions(planner, obs, repeat)
            rows.append([label, lever, f"{t:.2f} s", share, target])
    load = os.getloadavg()[0]
    header = ["planner", "world model", "s/decision (median)", "time share", "target", "threads, load"]
    rows = [r + [f"{torch.get_num_threads()}, {load:.1f}"] for r in rows]
    publish(f"Vision planners, one history, {torch.get_num_threads()} threads (load {load:.1f})", "vision_planners", header,
            rows, doc, key=2)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--policy", default=None, help="An image policy checkpoint (default: an untrained cpu-profile network).")
    parser.add_argument("--world-model", default=None, help="A visual world-model checkpoint.")
    parser.add_argument("--reward", default=None, help="A `gpc train reward` checkpoint.")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    run(args.doc, args.policy, args.world_model, args.reward, repeat=args.repeat)
