"""Seconds per decision of every planner for one observation history (a deployed robot's case).

Targets on 2 cores (issue 5): GPC-RANK K=100 <= 0.25 s, GPC-RANK+OPT K=10 M=30 <= 1 s.
Latency does not depend on the weights, so untrained networks of the ``cpu`` profiles are
timed unless checkpoints are given; scores come from ``make reproduce-pusht``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch

from benchmarks.bench_policy import _policy
from benchmarks.common import publish, time_decisions
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.planner import model_planner
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.models.world_models.state import STATE_KEY
from gpc.tasks import get_task
from gpc.tasks.pusht import LAYOUT, SimulatorModel, observe
from gpc.tasks.pusht.env import PushTEnv

SETTINGS = [  # (label, planner config fields, world model: learned | gt-sim, target)
    ("rank K=100", dict(kind="rank", num_proposals=100), "learned", "<= 0.25 s"),
    ("rank K=10", dict(kind="rank", num_proposals=10), "learned", ""),
    ("opt M=30", dict(kind="opt", num_proposals=1, opt_steps=30), "learned", ""),
    ("rank-opt 10x30", dict(kind="rank-opt", num_proposals=10, opt_steps=30), "learned", "<= 1 s"),
    ("gt-sim K=100", dict(kind="rank", num_proposals=100), "gt-sim", ""),
    ("cem 100x5", dict(kind="cem", num_proposals=100, opt_steps=5), "learned", ""),
    ("mppi 100x5", dict(kind="mppi", num_proposals=100, opt_steps=5), "learned", ""),
    ("grad 10x30", dict(kind="grad", num_proposals=10, opt_steps=30), "learned", ""),
]


def _world_model(profile: str = "cpu") -> WorldModelModule:
    config = world_model_profile(profile, 1, LAYOUT).config
    rng = np.random.default_rng(0)
    high, dim = LAYOUT.action.high, LAYOUT.state.dim
    normalizer = MinMaxNormalizer.fit({STATE_KEY: rng.uniform(0, high, (256, dim)),
                                       "action": rng.uniform(0, high, (256, LAYOUT.action.dim))})
    normalizer.add("state_delta", -np.ones(dim), np.ones(dim))
    return WorldModelModule(config, normalizer).eval()


def run(doc: Path | None, policy_ckpt: str | None = None, wm_ckpt: str | None = None, settings: list = SETTINGS,
        samplers: tuple[int, ...] = (10, 5), profile: str = "cpu") -> None:
    from gpc.models.policy.module import PolicyModule

    torch.manual_seed(0)
    policy = PolicyModule.load_from_checkpoint(policy_ckpt) if policy_ckpt else _policy(profile, "keypoints")
    learned = WorldModelModule.load_from_checkpoint(wm_ckpt) if wm_ckpt else _world_model(profile)
    reward = build_reward(RewardSpec(), get_task(LAYOUT.name))
    env = PushTEnv()
    env.reset(seed=100000)
    o = observe(env, images=False, sim=True)
    obs = {k: np.stack([v, v])[None] for k, v in o.items()}
    rows = []
    for steps in samplers:
        sampling = SamplingConfig("ddim", steps)
        for label, fields, model, target in settings:
            wm = SimulatorModel() if model == "gt-sim" else learned
            box = {"action_low": LAYOUT.action.low, "action_high": LAYOUT.action.high}
            planner = model_planner(PlannerConfig(**fields, **box), wm, reward, policy, sampling)
            t, share = time_decisions(planner, obs, 5)
            rows.append([label, f"DDIM-{steps}", f"{t:.3f} s", share, target])
    load = os.getloadavg()[0]
    header = ["planner", "policy sampling", "s/decision (median)", "time share", "target", "threads, load"]
    rows = [r + [f"{torch.get_num_threads()}, {load:.1f}"] for r in rows]
    publish(f"Planners, one history, {torch.get_num_threads()} threads (load {load:.1f})", "planners", header, rows, doc, key=2)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--policy", default=None, help="A policy checkpoint (default: an untrained cpu-profile network).")
    parser.add_argument("--world-model", default=None, help="A state world-model checkpoint.")
    args = parser.parse_args()
    run(args.doc, args.policy, args.world_model)
