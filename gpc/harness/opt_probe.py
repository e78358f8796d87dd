"""Why gradient ascent helps or not: every ascent iterate scored by the planner and by the true simulator.

A gradient planner (opt, rank-opt, grad) runs its closed-loop episodes as in ``gpc eval``; at each
decision its ascent is traced (``AscentTrace``) and every iterate, the proposal included, is
also replayed in the task's simulator and scored by the task's registration reward. Per ascent
step this gives the predicted gain, the true gain, how far the chunk moved and where the
gradient flows (per action, per predicted step). The world model's error on the iterate it
starts from and the one it returns tells a world model driven off its data (the error grows)
from a reward misreading faithful predictions (the error stays, the true gain does not come).
For image models the planner's reward also reads the true frames of both (rendered from the
simulator): its gain there splits the predicted-vs-true gap into the world model's share (the
reward is right on true frames, the predicted frames mislead it) and the reward's own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from gpc.harness.evaluation import EvalConfig, run_group
from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.planning.ascent import AscentTrace
from gpc.models.planning.objective import GOAL_KEY, Objective, PartTimer
from gpc.models.planning.planner import Planner
from gpc.models.planning.protocols import Plan
from gpc.models.world_models.eval_state import state_errors
from gpc.tasks import get_task
from gpc.tasks.base import Task


@dataclass
class Decision:
    """One decision's ascent: ``(B, K, M+1)`` predicted and true scores, its moves and gradients."""

    predicted: np.ndarray  # (B, K, M+1)
    true: np.ndarray  # (B, K, M+1)
    moved: np.ndarray  # (B, K, M+1): mean |a_m - a_0| over the chunk (action units)
    action_grads: np.ndarray  # (B, K, M, T)
    future_grads: np.ndarray  # (B, K, M, T')
    model_error: np.ndarray  # (B, K, 2): the world model's error on the final predicted step, start and end
    reward_on_truth: np.ndarray  # (B, K, 2): the planner's reward reading the true frames instead, start and end (NaN: states)
    chosen: np.ndarray  # (B,)


class ProbingPlanner:
    """A ``Controller``: the planner's own decisions, each traced and replayed in the true simulator."""

    def __init__(self, planner: Planner, task: Task) -> None:
        if not planner.config.uses_gradients:
            raise ValueError(f"--planner {planner.config.kind} takes no gradient steps; probe opt, rank-opt or grad")
        self.planner, self.task = planner, task
        self.simulator, self.truth = task.simulator(), build_reward(RewardSpec(), task)
        self.obs_keys = tuple(dict.fromkeys(planner.obs_keys + (task.sim_key,)))
        self.n_obs_steps, self.n_action_steps = planner.n_obs_steps, planner.n_action_steps
        self.decisions: list[Decision] = []

    def start(self, episodes: Any) -> None:
        self.planner.start(episodes)

    def plan(self, obs: dict[str, np.ndarray], generators: Any) -> Plan:
        trace = self.planner.trace = AscentTrace()
        try:
            plan = self.planner.plan(obs, generators)
        finally:
            self.planner.trace = None
        chunks = torch.stack(trace.chunks, dim=2)  # (B, K, M+1, T, A)
        b, k, m1 = chunks.shape[:3]
        goal = torch.as_tensor(np.asarray(obs[GOAL_KEY])[:, -1], dtype=torch.float32) if GOAL_KEY in obs else None
        sim = Objective(self.simulator, self.truth, torch.as_tensor(np.asarray(obs[self.task.sim_key])), goal, PartTimer())
        with torch.no_grad():
            true, true_futures = sim(chunks.flatten(1, 2))
            ends = chunks[:, :, [0, m1 - 1]]
            model = self.planner.scorer.objective(obs, PartTimer())
            _, predicted_ends = model(ends.flatten(1, 2))
        true_ends = true_futures.unflatten(1, (k, m1))[:, :, [0, m1 - 1]].flatten(1, 2)
        error, on_truth = self._against_truth(predicted_ends, true_ends, goal)
        self.decisions.append(Decision(
            predicted=torch.stack(trace.scores, dim=2).numpy(), true=true.unflatten(1, (k, m1)).numpy(),
            moved=(chunks - chunks[:, :, :1]).abs().mean(dim=(-1, -2)).numpy(),
            action_grads=torch.stack(trace.action_grads, dim=2).numpy(),
            future_grads=torch.stack(trace.future_grads, dim=2).numpy(),
            model_error=error.unflatten(1, (k, 2)).numpy(), reward_on_truth=on_truth.unflatten(1, (k, 2)).numpy(),
            chosen=np.asarray(plan.chosen)))
        return plan

    def _against_truth(self, predicted: torch.Tensor, true_states: torch.Tensor,
                     goal: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, N, T', ...)`` predictions, ``(B, N, T, D)`` true states -> ``(B, N)`` error on the last predicted step
        (the objects' vertex distance for state models, or the agent's where the task has no object; the pixel RMSE
        against the true frame for image models)
        and ``(B, N)`` the planner's reward reading that true frame (image models; NaN for state models)."""
        layout = self.task.layout
        nan = torch.full(predicted.shape[:2], float("nan"))
        if predicted.dim() == 4:  # state futures
            errors = state_errors(predicted[:, :, -1], true_states[:, :, -1], layout)
            return errors.get("registration_px", errors.get("agent_px", nan)), nan  # a drawing registers nothing: the pen
        frameskip = true_states.shape[2] // predicted.shape[2]
        last = true_states[:, :, predicted.shape[2] * frameskip - 1].numpy()
        goals_np = [None] * len(last) if goal is None else goal.numpy()  # drawn as the camera shows it (swap's targets)
        frames = np.stack([[self.task.render_state(s, g) for s in row] for row, g in zip(last, goals_np)])  # (B, N, S0, S0, C)
        as_frames = getattr(getattr(self.planner.world_model, "dynamics", None), "frames", None)  # stored images -> its frames
        if as_frames is None:
            return nan, nan
        truth = as_frames(torch.from_numpy(frames)).float()
        error = (predicted[:, :, -1].float() - truth).pow(2).flatten(2).mean(dim=-1).sqrt()
        b, n = truth.shape[:2]
        goals = None if goal is None else goal[:, None].expand(b, n, -1).flatten(0, 1)
        on_truth = self.planner.reward(truth.flatten(0, 1)[:, None], goals).unflatten(0, (b, n))  # a one-frame future
        return error, on_truth.float()


def probe(planner: Planner, task_name: str, seeds: tuple[int, ...], max_steps: int, batch: int, goal: str = "fixed",
          threads: int = 1) -> tuple[dict[str, Any], list[Decision]]:
    """Closed-loop episodes of ``planner`` with every decision probed -> (episode results, decisions)."""
    task = get_task(task_name)
    torch.set_num_threads(threads)
    controller = ProbingPlanner(planner, task)
    config = EvalConfig(seeds=seeds, task=task_name, goal=goal, max_steps=max_steps, batch=batch, threads=threads)
    episodes: list[dict[str, Any]] = []
    for group in config.groups():
        episodes += run_group(controller, group, config)["episodes"]  # type: ignore[arg-type]
    return {"episodes": episodes}, controller.decisions


def summarize(decisions: list[Decision]) -> dict[str, Any]:
    """Per ascent step, over every decision and candidate: gains (predicted, true), moves; gradients; the verdict."""
    cat = lambda name: np.concatenate([getattr(d, name).reshape(-1, *getattr(d, name).shape[2:]) for d in decisions])  # noqa: E731
    pred, true, moved = cat("predicted"), cat("true"), cat("moved")  # (N, M+1)
    dp, dt = pred - pred[:, :1], true - true[:, :1]
    chosen_rows, offset = [], 0  # each decision's executed candidates, as rows of the (N, M+1) arrays
    for d in decisions:
        b, k = d.predicted.shape[:2]
        chosen_rows.append(offset + np.arange(b) * k + d.chosen)
        offset += b * k
    executed = np.concatenate(chosen_rows)
    final_dp, final_dt = dp[:, -1], dt[:, -1]
    error, on_truth = cat("model_error"), cat("reward_on_truth")  # (N, 2) each
    truth_gain = on_truth[:, 1] - on_truth[:, 0]
    images = bool(np.isfinite(truth_gain).all())
    return {
        "decisions": sum(d.predicted.shape[0] for d in decisions), "candidates": int(pred.shape[0]), "steps": int(pred.shape[1] - 1),
        "per_step": {"predicted_gain_mean": dp.mean(0).tolist(), "true_gain_mean": dt.mean(0).tolist(),
                     "true_gain_median": np.median(dt, 0).tolist(), "moved_mean": moved.mean(0).tolist()},
        "final": {"predicted_gain_mean": float(final_dp.mean()), "true_gain_mean": float(final_dt.mean()),
                  "true_gain_of_chosen_mean": float(final_dt[executed].mean()),
                  "share_predicted_up": float((final_dp > 1e-6).mean()), "share_true_up": float((final_dt > 1e-6).mean()),
                  "share_fooled": float(((final_dp > 1e-6) & (final_dt < -1e-6)).mean()),
                  "gain_correlation": _correlation(final_dp, final_dt),
                  "moved_mean": float(moved[:, -1].mean())},
        "reward_on_true_frames": None if not images else {
            "gain_mean": float(truth_gain.mean()), "gain_correlation_with_true": _correlation(truth_gain, final_dt),
            "share_up": float((truth_gain > 1e-6).mean())},
        "selection": _selection(decisions),
        "model_error": {"start_mean": float(error[:, 0].mean()), "end_mean": float(error[:, 1].mean()),
                        "start_median": float(np.median(error[:, 0])), "end_median": float(np.median(error[:, 1]))},
        "gradient": {"per_action_first_step": cat("action_grads")[:, 0].mean(0).tolist(),
                     "per_predicted_step_first_step": cat("future_grads")[:, 0].mean(0).tolist(),
                     "action_norm_per_step": cat("action_grads").sum(-1).mean(0).tolist()},
    }


def _selection(decisions: list[Decision]) -> dict[str, float] | None:
    """With K > 1 candidates: the true gain per decision over the average proposal of picking by the predicted
    score before ascent (GPC-RANK), of the executed ascended chunk (RANK+OPT), and of the truly best proposal."""
    if decisions[0].predicted.shape[1] < 2:
        return None
    pred = np.concatenate([d.predicted for d in decisions])  # (D, K, M+1)
    true = np.concatenate([d.true for d in decisions])
    chosen, rows = np.concatenate([d.chosen for d in decisions]), np.arange(len(pred))
    mean = true[:, :, 0].mean(axis=1)
    ranked = pred[:, :, 0].argmax(axis=1)
    return {"rank_gain_mean": float((true[rows, ranked, 0] - mean).mean()),
            "executed_gain_mean": float((true[rows, chosen, -1] - mean).mean()),
            "ascent_on_rank_choice_gain_mean": float((true[rows, ranked, -1] - true[rows, ranked, 0]).mean()),
            "best_proposal_gain_mean": float((true[:, :, 0].max(axis=1) - mean).mean())}


def _correlation(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson correlation, or None where either side does not vary."""
    if a.std() < 1e-12 or b.std() < 1e-12:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def _truth_rows(truth: dict[str, Any] | None) -> list[str]:
    """The reward's gain read on the true frames (image models): where the predicted-vs-true gap comes from."""
    if truth is None:
        return []
    corr = "n/a" if truth["gain_correlation_with_true"] is None else f"{truth['gain_correlation_with_true']:+.2f}"
    return [f"| the planner's reward on the true last frames: gain, mean (share up; correlation with the true gain) | "
            f"{truth['gain_mean']:+.4f} ({truth['share_up']:.0%}; {corr}) |"]


def _selection_rows(selection: dict[str, float] | None) -> list[str]:
    """K > 1: what picking does, as true gains per decision over the average proposal."""
    if selection is None:
        return []
    return [f"| true gain over the average proposal: picked by predicted score before ascent (RANK) / executed after "
            f"ascent / truly best proposal | {selection['rank_gain_mean']:+.4f} / {selection['executed_gain_mean']:+.4f} / "
            f"{selection['best_proposal_gain_mean']:+.4f} |",
            f"| ascent from RANK's pick, true gain | {selection['ascent_on_rank_choice_gain_mean']:+.4f} |"]


def markdown(summary: dict[str, Any], title: str) -> str:
    """The probe's verdict as a short Markdown report."""
    f, e, s = summary["final"], summary["model_error"], summary["per_step"]
    corr = "n/a" if f["gain_correlation"] is None else f"{f['gain_correlation']:+.2f}"
    lines = [f"# {title}", "",
             f"{summary['decisions']} decisions (episode x step), {summary['candidates']} ascents of {summary['steps']} steps.", "",
             "| after the last step | value |", "|---|---|",
             f"| predicted gain, mean | {f['predicted_gain_mean']:+.4f} |",
             f"| true gain (simulator, task reward), mean | {f['true_gain_mean']:+.4f} |",
             f"| true gain of the executed candidate, mean | {f['true_gain_of_chosen_mean']:+.4f} |",
             f"| share predicted up / truly up | {f['share_predicted_up']:.0%} / {f['share_true_up']:.0%} |",
             f"| share fooled (predicted up, truly down) | {f['share_fooled']:.0%} |",
             f"| correlation of predicted and true gains | {corr} |",
             f"| mean move of an action (action units) | {f['moved_mean']:.2f} |",
             *_truth_rows(summary.get("reward_on_true_frames")),
             *_selection_rows(summary.get("selection")),
             f"| world-model error on the last predicted step, start -> end (mean; median) | "
             f"{e['start_mean']:.4g} -> {e['end_mean']:.4g}; {e['start_median']:.4g} -> {e['end_median']:.4g} |", "",
             "| step | predicted gain | true gain (mean / median) | move |", "|---|---|---|---|"]
    for m, (p, t, tm, mv) in enumerate(zip(s["predicted_gain_mean"], s["true_gain_mean"], s["true_gain_median"], s["moved_mean"])):
        lines.append(f"| {m} | {p:+.4f} | {t:+.4f} / {tm:+.4f} | {mv:.2f} |")
    return "\n".join(lines) + "\n"
