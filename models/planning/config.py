"""What a planner does at each decision, as one validated config (the CLI fills it).

``rank``, ``opt`` and ``rank-opt`` start from the frozen policy's proposals (GPC); ``cem``,
``mppi`` and ``grad`` start from random chunks (the paper's prior-free comparison); ``vgps``
ranks the proposals by a Q-function. The ground-truth-simulator ceiling is ``rank`` with the
simulator as world model. What each kind needs is in ``gpc.models.planning.registry``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from gpc.models.planning.protocols import ActionProposer
from gpc.models.planning.registry import BUILT_IN, WORLD_MODEL, PlannerKind, planner_kind

PLANNERS = tuple(k.name for k in BUILT_IN if k.load == WORLD_MODEL)  # the built-in planners over a world model
WITH_GRADIENTS = tuple(k.name for k in BUILT_IN if k.uses_gradients)  # (for messages; a kind says it of itself)
MAX_PROPOSALS = 100_000
LR_DECAYS = ("constant", "cosine")


@dataclass(frozen=True)
class PlannerConfig:
    """K proposals (or samples per iteration), M iterations, and the search's step sizes.

    ``opt`` refines one proposal (K is 1); ``rank`` takes no steps (M is 0). Actions stay inside
    ``[action_low, action_high]``, the task's action box, filled in by the caller (the planners
    that draw random chunks, ``cem``, ``mppi`` and ``grad``, need it; the others clip to it when given).
    """

    kind: str = "rank"  # a registered planner (gpc.models.planning.registry): rank | opt | rank-opt | cem | mppi | grad | vgps
    num_proposals: int = 100  # K: policy proposals, random initial chunks, or samples per CEM/MPPI iteration
    opt_steps: int = 0  # M: gradient-ascent steps (opt, rank-opt, grad) or CEM/MPPI iterations
    lr: float = 2.0  # Adam step size on the raw actions (action units, e.g. px)
    lr_decay: str = "constant"  # constant | cosine: the step size over the M steps (gpc.models.planning.ascent)
    trust_region: float = 0.0  # gradient planners: how far (action units) an action may move from its start; 0: anywhere
    keep_best: bool = False  # gradient planners: each candidate ends at its best-scoring iterate, the start included
    knots: int = 0  # gradient planners: ascend this many offsets interpolated over the chunk; 0: every action
    elite_fraction: float = 0.1  # CEM: share of samples refitted
    temperature: float = 2.0  # MPPI: softmax temperature, in reward units
    init_std: float = 0.25  # CEM/MPPI: initial std as a fraction of the action range
    action_low: float | None = None  # lower bound of every action entry (the task's)
    action_high: float | None = None  # upper bound of every action entry (the task's)
    keep_futures: bool = False  # return every candidate's predicted future (for videos; memory grows with K)
    # Actions executed per decision (None: the policy's n_action_steps); the whole chunk, e.g., to record the true
    # outcome of every action the reward judged (`gpc record`).
    action_steps: int | None = None

    def __post_init__(self) -> None:
        kind = self.planner  # an unknown name fails here, naming the known ones
        if self.action_steps is not None and self.action_steps < 1:
            raise ValueError(f"--action-steps {self.action_steps}: must be at least 1")
        if not 1 <= self.num_proposals <= MAX_PROPOSALS:
            raise ValueError(f"--K {self.num_proposals}: must lie in 1..{MAX_PROPOSALS}")
        if kind.single and self.num_proposals != 1:
            raise ValueError(f"--K {self.num_proposals}: {self.kind} refines one proposal (use rank-opt for several)")
        if not 0 <= self.opt_steps <= 10_000:
            raise ValueError(f"--M {self.opt_steps}: must lie in 0..10000")
        if kind.iterates and self.opt_steps < 1:
            raise ValueError(f"--M {self.opt_steps}: {self.kind} needs at least one step")
        if not kind.iterates and self.opt_steps:
            raise ValueError(f"--M {self.opt_steps}: {self.kind} takes no steps (rank-opt ranks and refines)")
        if not 0 < self.lr < math.inf:  # NaN fails too
            raise ValueError(f"--lr {self.lr}: the step size must be a finite number > 0")
        if self.lr_decay not in LR_DECAYS:
            raise ValueError(f"--lr-decay {self.lr_decay!r}: use one of {', '.join(LR_DECAYS)}")
        if not 0 <= self.trust_region < math.inf:
            raise ValueError(f"--trust-region {self.trust_region}: must be a finite number >= 0 (0: no limit)")
        if not 0 <= self.knots <= 10_000:
            raise ValueError(f"--knots {self.knots}: must lie in 0..10000 (0: every action is ascended)")
        if self.temperature <= 0:
            raise ValueError(f"temperature {self.temperature}: MPPI's softmax temperature must be > 0")
        if not 0 < self.init_std <= 1:
            raise ValueError(f"init_std {self.init_std}: must lie in (0, 1] (a share of the action range)")
        if not 0 < self.elite_fraction <= 1:
            raise ValueError(f"--elite-fraction {self.elite_fraction}: must lie in (0, 1]")
        if (self.action_low is None) != (self.action_high is None):
            raise ValueError("action bounds: give both action_low and action_high, or neither")
        if self.action_low is not None and self.action_high is not None and self.action_low >= self.action_high:
            raise ValueError(f"action bounds ({self.action_low}, {self.action_high}): low must be below high")
        if kind.prior_free and self.action_low is None:
            raise ValueError(f"--planner {self.kind} draws random chunks and needs the action box (action_low, action_high)")

    @property
    def planner(self) -> PlannerKind:
        """What this kind of planner is and needs (its registration)."""
        return planner_kind(self.kind)

    @property
    def uses_policy(self) -> bool:
        return self.planner.uses_policy

    @property
    def uses_gradients(self) -> bool:
        return self.planner.uses_gradients

    @property
    def box(self) -> tuple[float, float]:
        """The action box, for the planners that need one (the prior-free ones)."""
        if self.action_low is None or self.action_high is None:
            raise ValueError(f"planner {self.kind} needs the action box (action_low, action_high)")
        return self.action_low, self.action_high

    @property
    def label(self) -> str:
        """Short name for tables: ``rank K=100``, ``vgps K=100``, ``rank-opt 10x30``, ``opt M=30``."""
        if not self.planner.iterates:
            return f"{self.kind} K={self.num_proposals}"
        if self.planner.single:
            return f"{self.kind} M={self.opt_steps}"
        return f"{self.kind} {self.num_proposals}x{self.opt_steps}"


@dataclass(frozen=True)
class SamplingConfig:
    """How the policy samples at deployment (``None``: the checkpoint's own setting)."""

    method: str | None = None  # ddim | ddpm
    steps: int | None = None  # denoising steps
    spacing: str | None = None  # leading | trailing (see gpc.models.networks.ddpm)

    def __post_init__(self) -> None:
        if self.method not in (None, "ddim", "ddpm"):
            raise ValueError(f"--method {self.method!r}: use ddim or ddpm")
        if self.steps is not None and self.steps < 1:
            raise ValueError(f"--steps {self.steps}: must be at least 1")
        if self.spacing not in (None, "leading", "trailing"):
            raise ValueError(f"--spacing {self.spacing!r}: use leading or trailing")

    def sample(self, policy: ActionProposer, obs: Mapping[str, Any], k: int, generators: Sequence[torch.Generator]) -> torch.Tensor:
        """``(B, K, horizon, A)`` proposals from ``policy`` with this sampler (one generator per history)."""
        return policy.sample_batch(obs, k, list(generators), method=self.method, steps=self.steps, spacing=self.spacing)
