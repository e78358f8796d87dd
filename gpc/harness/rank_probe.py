"""How well a scorer orders the policy's proposals: its scores against the true simulator's on the same K chunks.

A ranking planner (GPC-RANK, V-GPS, the latent-model baselines) is only as good as the order its scorer puts the
policy's K proposals in, and closed-loop scores mix that with where the episodes go. This probe separates it: at
every decision of BC's own episodes (each executes the policy's first proposal, so every scorer is judged on the
same states) the K proposals are scored by each scorer and replayed in the task's simulator with the task's
reward (the ceiling's scores). Per scorer it reports the Spearman correlation with the truth, how often its pick
is the truly best chunk, and the true reward its pick gives up against the best (its regret), beside the regret of
a pick at random (the best minus the proposals' mean).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from gpc.harness.evaluation import EvalConfig, run_group
from gpc.harness.recipes import RewardSpec, build_reward
from gpc.harness.replays import ReplayLog
from gpc.models.planning.objective import GOAL_KEY, Objective, PartTimer
from gpc.models.planning.planner import Planner
from gpc.models.planning.protocols import Plan
from gpc.models.stats import spearman
from gpc.tasks.base import STATE_KEY, Task


class RankProbe:
    """A ``Controller``: BC's decisions (the first proposal), with every scorer and the simulator scoring all K.

    ``proposer``: the planner whose policy proposes (default: the first scorer's); ``replays``: where the replayed
    proposals are kept as training episodes (``gpc.harness.replays``)."""

    def __init__(self, planners: Mapping[str, Planner], task: Task, k: int, proposer: Planner | None = None,
                 replays: ReplayLog | None = None) -> None:
        first = proposer or next(iter(planners.values()))
        self.planners, self.task, self.k, self.proposer, self.replays = dict(planners), task, k, first, replays
        self.simulator, self.truth = task.simulator(), build_reward(RewardSpec(), task)
        every = [first, *planners.values()]
        keys = [key for p in every for key in p.obs_keys] + [task.sim_key] + ([STATE_KEY] if replays else [])
        self.obs_keys = tuple(dict.fromkeys(keys))
        self.n_obs_steps = max([p.n_obs_steps for p in every] + ([replays.history] if replays else []))
        self.n_action_steps = first.n_action_steps
        self.rows: dict[str, list[tuple[float, bool, float]]] = {name: [] for name in planners}
        self.random_regret: list[float] = []
        self.seeds: list[int] = []

    def start(self, episodes: Sequence[int]) -> None:
        self.seeds = list(episodes)
        for planner in dict.fromkeys([self.proposer, *self.planners.values()]):
            planner.start(episodes)

    def plan(self, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator]) -> Plan:
        timer = PartTimer()
        chunks = self.proposer.proposals(obs, self.k, generators, timer)  # the same K chunks for every scorer
        goal = torch.as_tensor(np.asarray(obs[GOAL_KEY])[:, -1], dtype=torch.float32) if GOAL_KEY in obs else None
        sim = Objective(self.simulator, self.truth, torch.as_tensor(np.asarray(obs[self.task.sim_key])), goal, timer)
        with torch.no_grad():
            true_scores, futures = sim(chunks)
            true = true_scores.cpu().numpy()
            for name, planner in self.planners.items():
                scores = planner.scorer.objective(obs, timer, planner.episodes)(chunks)[0].detach().cpu().numpy()
                for b in range(len(true)):
                    pick = int(scores[b].argmax())
                    best = float(true[b].max())
                    self.rows[name].append((spearman(scores[b], true[b]), pick == int(true[b].argmax()), best - float(true[b][pick])))
        self.random_regret.extend((true.max(axis=1) - true.mean(axis=1)).tolist())
        chunk = chunks[:, 0].cpu().numpy()
        if self.replays is not None:
            self.replays.add(self.seeds, np.asarray(obs[STATE_KEY]), chunks.cpu().numpy(), futures.cpu().numpy(),
                             chunk[:, : self.n_action_steps])
        return Plan(actions=chunk[:, : self.n_action_steps], chunk=chunk, seconds=timer.seconds)

    def summary(self) -> dict[str, Any]:
        random = float(np.mean(self.random_regret))
        out: dict[str, Any] = {"decisions": len(self.random_regret), "random_regret": random, "scorers": {}}
        for name, rows in self.rows.items():
            rho, top, regret = (np.array(v, dtype=float) for v in zip(*rows))
            out["scorers"][name] = {"spearman_mean": float(np.nanmean(rho)), "spearman_median": float(np.nanmedian(rho)),
                                    "picks_best": float(top.mean()), "regret": float(regret.mean()),
                                    "margin_kept": float(1.0 - regret.mean() / random) if random > 0 else float("nan")}
        return out


def probe_ranking(planners: Mapping[str, Planner], task: Task, seeds: tuple[int, ...], k: int, max_steps: int, batch: int,
                  goal: str = "fixed", proposer: Planner | None = None, replays: ReplayLog | None = None) -> dict[str, Any]:
    """Run BC's episodes on ``seeds`` in lockstep groups of ``batch``, scoring every decision's K proposals."""
    probe = RankProbe(planners, task, k, proposer, replays)
    scores: list[float] = []
    for i in range(0, len(seeds), batch):
        group = seeds[i : i + batch]
        config = EvalConfig(seeds=group, task=task.name, goal=goal, max_steps=max_steps, batch=len(group))
        scores.extend(r["score"] for r in run_group(probe, group, config)["episodes"])
    return {**probe.summary(), "bc_score": float(np.mean(scores))}


def markdown(summary: Mapping[str, Any], title: str) -> str:
    """The probe's table: one row per scorer."""
    lines = [f"# {title}", "", f"{summary['decisions']} decisions of BC's episodes (mean score {summary['bc_score']:.3f}); "
             f"a pick at random gives up {summary['random_regret']:.2f} of the best proposal's true reward.", "",
             "| scorer | Spearman with the truth (mean / median) | picks the truly best | regret of its pick | margin over random kept |",
             "|---|---|---|---|---|"]
    for name, s in summary["scorers"].items():
        lines.append(f"| {name} | {s['spearman_mean']:+.3f} / {s['spearman_median']:+.3f} | {s['picks_best']:.0%} | "
                     f"{s['regret']:.2f} | {s['margin_kept']:+.0%} |")
    return "\n".join(lines) + "\n\nregret: the true reward of the best of the K proposals minus that of the scorer's pick (task units).\n"
