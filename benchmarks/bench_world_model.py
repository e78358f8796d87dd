"""World models on the CPU: rollout latency for K proposals of T = 16 actions, and one gradient
step on the actions through model + reward (what GPC-OPT pays per iteration).

State model (cpu profile, MLP) scored by the registration reward; visual model (cpu or paper
profile, ``--profile``, EDM U-Net, frozen noise) scored by the learned image reward (the ResNet18
pose reader of the same profile, reading the final predicted frame, as in the planners). Latency
does not depend on the weights, so untrained networks of the profiles' shapes are timed unless
checkpoints are given.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import median_seconds, show, write_rows
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.rewards.learned import IMAGE_KEY, ImageReward, PosePredictor, reward_profile
from gpc.models.rewards.registration import PoseReward, RegistrationReward
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.models.world_models.state import ACTION_KEY, DELTA_KEY, STATE_KEY
from gpc.tasks.pusht import LAYOUT

KS = (1, 16, 100)
T = 16
STATE_HIGH = np.array([512.0, 512.0, 512.0, 512.0, 2 * math.pi])  # agent x, y, block x, y, angle


def _model(obs: str, checkpoint: str | None, profile: str = "cpu") -> WorldModelModule:
    if checkpoint:
        return WorldModelModule.load_from_checkpoint(checkpoint)
    norm = MinMaxNormalizer()
    norm.add(ACTION_KEY, np.zeros(2), np.full(2, 512.0))
    if obs == "state":
        norm.add(STATE_KEY, np.zeros(5), STATE_HIGH)
        norm.add(DELTA_KEY, -np.array([10.0, 10.0, 2.0, 2.0, 0.02]), np.array([10.0, 10.0, 2.0, 2.0, 0.02]))
    torch.manual_seed(0)
    return WorldModelModule(world_model_profile(profile, 1, LAYOUT, obs=obs).config, normalizer=norm).eval()


def _reward(obs: str, checkpoint: str | None, profile: str) -> PoseReward:
    if obs == "state":
        return RegistrationReward.from_layout(LAYOUT)
    if checkpoint:
        return ImageReward.from_checkpoint(checkpoint, LAYOUT.goal)
    config = reward_profile(profile, LAYOUT).config
    norm = MinMaxNormalizer()
    norm.add(IMAGE_KEY, np.zeros(3), np.full(3, 255.0))
    norm.add(STATE_KEY, np.zeros(5), STATE_HIGH)
    torch.manual_seed(0)
    return ImageReward(PosePredictor(config, norm).requires_grad_(False).eval())


def _inputs(model: WorldModelModule, obs: str, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(k)
    n = model.n_obs_steps
    if obs == "state":
        history = torch.rand(n, 5, generator=g) * torch.tensor([400.0, 400.0, 200.0, 200.0, 6.0]) + 50
    else:
        s = model.config.dynamics.resolution
        history = torch.rand(n, 3, s, s, generator=g)
    return history, torch.rand(k, T, 2, generator=g) * 400 + 50


def rows_for(obs: str, checkpoint: str | None, profile: str = "cpu", ks: tuple[int, ...] = KS,
             reward_checkpoint: str | None = None) -> list[list[str]]:
    profile = profile if obs == "image" else "cpu"  # the state model has one profile
    model = _model(obs, checkpoint, profile)
    reward = _reward(obs, reward_checkpoint, profile)
    params = sum(p.numel() for p in model.parameters()) / 1e6
    source = Path(checkpoint).name if checkpoint else f"{profile} profile"
    scorer = "registration" if obs == "state" else "learned reward"
    label = f"{obs} ({source}, {params:.2f}M params; {scorer})"
    rows = []
    for k in ks:
        history, actions = _inputs(model, obs, k)

        def roll() -> None:
            with torch.no_grad():
                model.rollout(history, actions)

        def grad_step() -> None:
            a = actions.clone().requires_grad_(True)
            futures = model.rollout(history, a)
            reward(futures).sum().backward()

        repeat = 3 if obs == "image" and (k == 100 or profile == "paper") else 7
        number = 20 if obs == "state" else 1
        r = median_seconds(roll, number=number, repeat=repeat)
        g = median_seconds(grad_step, number=number, repeat=repeat)
        target = "rollout <= 20 ms" if obs == "state" and k == 100 else ""  # issue 4, on 2 cores
        rows.append([label, f"K={k}, T={T}, frameskip {getattr(model.config.dynamics, 'frameskip', 1)}", f"{r * 1e3:,.1f} ms",
                     f"{g * 1e3:,.1f} ms", target])
    return rows


def run(doc: Path | None, state_checkpoint: str | None = None, image_checkpoint: str | None = None,
        kinds: tuple[str, ...] = ("state", "image"), profile: str = "cpu", ks: tuple[int, ...] = KS,
        reward_checkpoint: str | None = None) -> None:
    checkpoints = {"state": state_checkpoint, "image": image_checkpoint}
    rows = [row for kind in kinds for row in rows_for(kind, checkpoints[kind], profile, ks, reward_checkpoint)]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    header = ["model", "setting", "rollout (median)", "grad step: model + reward (median)", "target"]
    show(f"World model rollouts, {torch.get_num_threads()} threads (load {load:.1f})", header, rows)
    if doc:
        write_rows(doc, "world_model", header + ["threads, load"], [r + [f"{torch.get_num_threads()}, {load:.1f}"] for r in rows], 2)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--doc", type=Path, default=None)
    parser.add_argument("--state-checkpoint", default=None)
    parser.add_argument("--image-checkpoint", default=None)
    parser.add_argument("--reward-checkpoint", default=None,
                        help="a `gpc train reward` checkpoint to score the visual model's frames "
                             "(the state model uses the registration reward)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--profile", choices=("cpu", "paper"), default="cpu", help="visual model profile (untrained)")
    parser.add_argument("--ks", default=",".join(map(str, KS)), help="proposal counts, comma-separated")
    parser.add_argument("--obs", choices=("state", "image", "both"), default="both", help="which world models to time")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    run(args.doc, args.state_checkpoint, args.image_checkpoint,
        ("state", "image") if args.obs == "both" else (args.obs,), args.profile, tuple(int(k) for k in args.ks.split(",")),
        args.reward_checkpoint)
