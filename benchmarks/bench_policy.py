"""Diffusion Policy on the CPU: training throughput per profile, sampling latency per setting.

Sampling target (issue 3): K=100 proposals from the state policy in <= 150 ms on 2 cores.
Latency does not depend on the weights, so an untrained network of the profile's shape is
timed unless ``--checkpoint`` is given; scores for each setting come from ``gpc eval``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import median_seconds, publish
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import IMAGE_KEYS
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.tasks.pusht import LAYOUT

SHAPES = {"state": (5,), "keypoint": (9, 2), "img": (96, 96, 3)}


def _policy(profile: str, obs: str) -> PolicyModule:
    config = policy_profile(profile, obs, LAYOUT).config
    config = config.with_obs_shapes({k: SHAPES[k] for k in config.obs_keys})
    rng = np.random.default_rng(0)
    data = {k: rng.uniform(0, 512, (64,) + SHAPES[k]) for k in config.obs_keys} | {"action": rng.uniform(0, 512, (64, 2))}
    return PolicyModule(config, normalizer=MinMaxNormalizer.fit(data, image_keys=IMAGE_KEYS))


def _batch(policy: PolicyModule, n: int) -> dict[str, torch.Tensor]:
    c = policy.config
    out = {k: torch.rand((n, c.n_obs_steps) + SHAPES[k]) * 512 for k in c.obs_keys}
    out["action"] = torch.rand(n, c.horizon, c.action_dim) * 512
    return out


def train_rows(profiles: list[str], obs: str) -> list[list[str]]:
    rows = []
    for name in profiles:
        prof = policy_profile(name, obs, LAYOUT)
        policy = _policy(name, obs)
        opt = torch.optim.AdamW(policy.model.parameters(), lr=1e-4)
        batch = _batch(policy, prof.batch_size)

        def step() -> None:
            loss, _ = policy.model.loss(*policy._split_batch(batch))
            opt.zero_grad()
            loss.backward()
            opt.step()

        t = median_seconds(step, number=1, repeat=3 if name == "paper" else 7)
        params = sum(p.numel() for p in policy.model.parameters()) / 1e6
        rows.append([f"train {obs} {name} ({params:.1f}M params)", f"batch {prof.batch_size}",
                     f"{prof.batch_size / t:,.0f} samples/s", f"{t * 1e3:,.0f} ms/step", ""])
    return rows


def sample_rows(policy: PolicyModule, label: str) -> list[list[str]]:
    rows = []
    history = {k: v[0] for k, v in _batch(policy, 1).items() if k != "action"}
    for method, steps in (("ddim", 5), ("ddim", 10), ("ddpm", 100)):
        for k in (1, 10, 100):
            gen = torch.Generator().manual_seed(0)
            t = median_seconds(lambda: policy.sample(history, k, gen, method=method, steps=steps),
                               number=1, repeat=3 if method == "ddpm" else 7)
            target = "<= 150 ms" if k == 100 else ""
            rows.append([f"sample {label}", f"{method.upper()}-{steps}, K={k}", "", f"{t * 1e3:,.0f} ms", target])
    return rows


def run(doc: Path | None, checkpoint: str | None = None, obs: str = "keypoints") -> None:
    torch.manual_seed(0)
    rows = train_rows(["tiny", "cpu", "paper"], obs)
    policy = PolicyModule.load_from_checkpoint(checkpoint) if checkpoint else _policy("cpu", obs)
    rows += sample_rows(policy, f"{obs} cpu profile" if not checkpoint else Path(checkpoint).name)
    header = ["work", "setting", "throughput", "latency (median)", "target"]
    publish(f"Diffusion Policy ({obs} obs), {torch.get_num_threads()} threads", "policy", header, rows, doc, key=2)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--obs", choices=["state", "keypoints", "image"], default="keypoints")
    args = parser.parse_args()
    run(args.doc, args.checkpoint, args.obs)
