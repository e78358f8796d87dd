"""Gradient ascent on action chunks through world model and reward (GPC-OPT, RANK+OPT, prior-free grad).

Adam on the raw actions, every candidate at once (Adam acts per entry, and each candidate's score
depends on its own chunk only). Three guards, each off by default (the paper's plain ascent):

- ``lr_decay="cosine"``: the step size decays to 0 over the M steps, so the last steps refine;
- ``trust_region`` r: every action stays within r (action units) of the chunk ascent started from,
  where the world model was trained (the policy's proposals look like its data; far-off chunks may
  fool a learned model and reward);
- ``keep_best``: each candidate ends at its best-scoring iterate (the start included), so ascent
  never returns a chunk the objective itself scores below the proposal.

``knots`` n > 0 ascends n evenly spaced offsets, linearly interpolated over the chunk, instead of every
action: the proposal can only bend smoothly, so ascent cannot fool the models with step-to-step wiggles
no demonstration or exploration chunk has (the trust region then bounds the offsets, hence every action).

``AscentTrace`` records what each step did (scores, gradients per action and per predicted step,
how far the chunk moved), for the diagnostics in ``gpc.harness.opt_probe``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from gpc.models.planning.objective import Objective, PartTimer


@dataclass
class AscentTrace:
    """Per ascent step m = 0..M (m = M: the returned chunks): ``(B, K, ...)`` tensors, detached, on the CPU."""

    chunks: list[torch.Tensor] = field(default_factory=list)  # (B, K, T, A) the iterate scored at step m
    scores: list[torch.Tensor] = field(default_factory=list)  # (B, K) its predicted score
    action_grads: list[torch.Tensor] = field(default_factory=list)  # (B, K, T) |d score / d action_t|, steps 0..M-1
    future_grads: list[torch.Tensor] = field(default_factory=list)  # (B, K, T') |d score / d future_t|, steps 0..M-1


def step_size(config: Any, m: int) -> float:
    """Adam's step size at ascent step ``m`` of ``config.opt_steps``."""
    if config.lr_decay == "cosine":
        return config.lr * 0.5 * (1.0 + math.cos(math.pi * m / config.opt_steps))
    return config.lr


def _norms(grad: torch.Tensor | None, like: torch.Tensor, dims: int) -> torch.Tensor:
    """Euclidean norm over the trailing ``dims`` dimensions (zeros where nothing flowed)."""
    if grad is None:
        return torch.zeros(like.shape[: like.dim() - dims])
    return grad.detach().flatten(like.dim() - dims).norm(dim=-1).cpu()


def ascend(objective: Objective, init: torch.Tensor, config: Any, timer: PartTimer,
           trace: AscentTrace | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """M Adam steps on ``(B, K, T, A)`` chunks -> the chunks, their scores ``(B, K)`` and futures ``(B, K, T', ...)``.

    ``config`` is a ``PlannerConfig`` (``opt_steps``, ``lr``, ``lr_decay``, ``trust_region``,
    ``keep_best``, ``knots`` and the action box).
    """
    start = init.detach()
    knots = config.knots
    if knots:  # the offsets ascended, and the chunk they bend the start into
        basis = interpolation(start.shape[-2], knots).to(start)
        variable = start.new_zeros(*start.shape[:-2], knots, start.shape[-1]).requires_grad_(True)
        lo, hi = _knot_bounds(start, basis, config)
    else:
        variable = start.clone().requires_grad_(True)
        lo, hi = _action_bounds(start, config)
    optimizer = torch.optim.Adam([variable], lr=config.lr)
    best: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    with torch.enable_grad():
        for m in range(config.opt_steps):
            actions = variable
            if knots:
                actions = start + basis @ variable
                actions.retain_grad()
            scores, futures = objective(actions)
            with timer("optimizer"):
                if config.keep_best:
                    best = _better(best, actions.detach(), scores.detach(), futures.detach())
                if trace is not None:
                    futures.retain_grad()
                for group in optimizer.param_groups:
                    group["lr"] = step_size(config, m)
                optimizer.zero_grad(set_to_none=True)
                (-scores.sum()).backward()
                if trace is not None:
                    trace.chunks.append(actions.detach().cpu().clone())
                    trace.scores.append(scores.detach().cpu())
                    trace.action_grads.append(_norms(actions.grad, actions, 1))
                    trace.future_grads.append(_norms(futures.grad, futures, futures.dim() - 3))
                optimizer.step()
                if lo is not None and hi is not None:
                    with torch.no_grad():  # projected back, so a bound that stops binding lets the entry move again
                        variable.copy_(torch.maximum(torch.minimum(variable, hi), lo))
    with torch.no_grad():
        chunks = variable.detach()
        if knots:
            chunks = start + basis @ chunks
            if config.action_low is not None:  # (rounding only: the knots' bounds keep every action in the box)
                chunks = chunks.clamp(config.action_low, config.action_high)
        scores, futures = objective(chunks)
    if config.keep_best:
        chunks, scores, futures = _better(best, chunks, scores, futures)
    if trace is not None:
        trace.chunks.append(chunks.cpu().clone())
        trace.scores.append(scores.cpu())
    return chunks, scores, futures


def _action_bounds(start: torch.Tensor, config: Any) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Per action entry: the action box, narrowed to the trust region around the start (None: unbounded)."""
    low, high = config.action_low, config.action_high
    if config.trust_region > 0:
        lo, hi = start - config.trust_region, start + config.trust_region
        return (lo.clamp(low, high), hi.clamp(low, high)) if low is not None else (lo, hi)
    if low is not None:
        return torch.full_like(start, low), torch.full_like(start, high)
    return None, None


def _knot_bounds(start: torch.Tensor, basis: torch.Tensor, config: Any) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """Per knot offset ``(..., knots, A)``: what keeps every action it blends into inside its own bounds.

    An action's offset is a convex blend of its knots', so a knot within every bound of the actions it
    touches keeps them all inside (with a knot per action: the plain ascent's bounds exactly).
    """
    lo, hi = _action_bounds(start, config)
    if lo is None or hi is None:
        return None, None
    touches = (basis > 0).T[..., None]  # (knots, T, 1): the actions each knot moves
    lo = torch.where(touches, (lo - start).unsqueeze(-3), -torch.inf).amax(dim=-2)
    hi = torch.where(touches, (hi - start).unsqueeze(-3), torch.inf).amin(dim=-2)
    return lo, torch.maximum(hi, lo)  # (a start outside the box on both sides of one knot: the lower bound wins)


def interpolation(steps: int, knots: int) -> torch.Tensor:
    """``(steps, knots)`` weights: each step a linear blend of its two neighbouring knots (one knot: a shift)."""
    if knots == 1:
        return torch.ones(steps, 1)
    where = torch.linspace(0, knots - 1, steps)
    left = where.floor().clamp(max=knots - 2).long()
    right_weight = where - left
    weights = torch.zeros(steps, knots)
    weights[torch.arange(steps), left] = 1 - right_weight
    weights[torch.arange(steps), left + 1] = right_weight
    return weights


def _better(best: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None, chunks: torch.Tensor, scores: torch.Tensor,
            futures: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per candidate, the higher-scoring of the best so far and this iterate (ties keep the earlier)."""
    if best is None:
        return chunks.clone(), scores.clone(), futures.clone()
    up = scores > best[1]
    return (torch.where(up[..., None, None], chunks, best[0]), torch.where(up, scores, best[1]),
            torch.where(up.view(*up.shape, *[1] * (futures.dim() - 2)), futures, best[2]))
