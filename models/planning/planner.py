"""GPC's planners and the prior-free baselines: one class per search behind one ``Controller`` interface.

A decision for B observation histories (lockstep episodes) works on ``B * K`` candidate
chunks at once: the policy proposes ``(B, K, T, A)`` chunks in one batched call, the world
model rolls all ``B * K`` out in one call, the reward scores them in one call, and each
history executes its best candidate. Gradient steps (GPC-OPT, RANK+OPT, prior-free ``grad``)
update all candidates together; Adam acts per entry and every candidate's reward depends on
its own chunk only, so optimising K chunks as one batch equals optimising them one by one.

Chunks here run from the current step on (``T = horizon - n_obs_steps + 1`` actions); the
world model predicts the state after each of them, and the reward scores those futures. The
scoring is the ``Scorer``'s (``objective.ModelScorer`` for a world model and a reward; a Q-function
for V-GPS), the search is the class's: ``Rank``, ``Opt`` (GPC-OPT, RANK+OPT, prior-free gradient
ascent), ``CEM``, ``MPPI``. ``build_planner`` picks the class a config's kind registered
(``gpc.models.planning.registry``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from gpc.models.planning.ascent import AscentTrace, ascend
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.objective import ModelScorer, Objective, PartTimer
from gpc.models.planning.protocols import ActionProposer, Plan, Reward, Scorer, WorldModel

Found = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # (B, K, T, A) chunks, (B, K) scores, (B, K, ...) predictions


class Planner:
    """A ``Controller`` over a scorer: each decision proposes or draws candidates, searches, executes the best.

    Subclasses supply ``search``; the rest (the timeline, observation keys, the ``Plan``) is shared.
    """

    def __init__(self, config: PlannerConfig, scorer: Scorer, policy: ActionProposer | None = None,
                 sampling: SamplingConfig = SamplingConfig(), horizon: int | None = None,
                 n_action_steps: int | None = None, action_dim: int | None = None) -> None:
        if config.uses_policy and policy is None:
            raise ValueError(f"planner {config.kind} needs a policy checkpoint")
        if config.uses_gradients and not scorer.differentiable:
            raise ValueError(f"planner {config.kind} needs a differentiable score; a selecting reward only ranks")
        self.config, self.scorer, self.policy, self.sampling = config, scorer, policy, sampling
        if policy is not None:
            pc = policy.config
            self.now = pc.n_obs_steps - 1  # index of the current step in a policy chunk
            self.horizon = pc.horizon - self.now
            self.n_action_steps = config.action_steps or pc.n_action_steps
            self.obs_keys = tuple(dict.fromkeys(policy.obs_keys + scorer.obs_keys))
            self.n_obs_steps = max(pc.n_obs_steps, scorer.n_obs_steps)
            self.action_dim = pc.action_dim
        else:
            if horizon is None or n_action_steps is None or action_dim is None:
                raise ValueError("a planner without a policy needs horizon, n_action_steps and action_dim")
            self.now, self.horizon, self.action_dim = 0, horizon, action_dim
            self.n_action_steps = config.action_steps or n_action_steps
            self.obs_keys, self.n_obs_steps = scorer.obs_keys, scorer.n_obs_steps
        if not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"--action-steps {self.n_action_steps}: must lie in 1..{self.horizon} (the actions a chunk plans)")
        if config.knots > self.horizon:
            raise ValueError(f"--knots {config.knots}: at most {self.horizon}, the actions a chunk plans")
        self.episodes: Sequence[int] | None = None
        self.trace: AscentTrace | None = None  # set one to record the next decisions' gradient ascent (diagnostics)

    @property
    def world_model(self) -> Any:
        """The world model GPC's scorer rolls out (None for a scorer without one)."""
        return getattr(self.scorer, "world_model", None)

    @property
    def reward(self) -> Any:
        return getattr(self.scorer, "reward", None)

    def start(self, episodes: Sequence[int]) -> None:
        """The harness names the episodes (seeds) of the next decisions' histories: the lockstep group's before
        its first decision, the unfinished ones whenever some finish."""
        self.episodes = list(episodes)

    def stats(self) -> dict[str, Any]:
        """The scorer's counters (a VLM reward's queries and fallbacks), summed over every decision so far."""
        stats = getattr(self.scorer, "stats", None)
        return dict(stats()) if callable(stats) else {}

    # ------------------------------------------------------------------ the decision
    def plan(self, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator]) -> Plan:
        timer = PartTimer()
        objective = self.scorer.objective(obs, timer, self.episodes)
        chunks, scores, futures = self.search(objective, obs, generators, timer)
        best = scores.argmax(dim=1)
        rows = torch.arange(chunks.shape[0])
        chunk = chunks[rows, best].detach().cpu().numpy()
        keep = self.config.keep_futures
        return Plan(
            actions=chunk[:, : self.n_action_steps], chunk=chunk, seconds=timer.seconds,
            scores=scores.detach().cpu().numpy(), chosen=best.cpu().numpy(),
            futures=futures.detach().cpu().numpy() if keep else None,
            candidates=chunks.detach().cpu().numpy() if keep else None,
        )

    def act(self, obs_history: Mapping[str, Any], generator: torch.Generator | None = None) -> np.ndarray:
        """Deployment: ``{key: (H, ...)}`` one raw observation history -> ``(T, A)`` chunk from now on."""
        batched = {k: np.asarray(v)[None] for k, v in obs_history.items()}
        with torch.no_grad():
            return self.plan(batched, [generator if generator is not None else torch.Generator()]).chunk[0]

    def search(self, objective: Objective, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator],
               timer: PartTimer) -> Found:
        """The candidates after the search, with their scores and predictions."""
        raise NotImplementedError

    # ------------------------------------------------------------------ where candidates start
    def proposals(self, obs: Mapping[str, np.ndarray], k: int, generators: Sequence[torch.Generator],
                  timer: PartTimer) -> torch.Tensor:
        """``(B, K, T, A)``: the policy's K proposals for each history, from the current step on."""
        assert self.policy is not None  # __init__ refuses a policy planner without one
        with timer("policy"):
            return self.sampling.sample(self.policy, obs, k, generators)[:, :, self.now :].float()

    def uniform(self, generators: Sequence[torch.Generator], b: int) -> torch.Tensor:
        """``(B, K, T, A)`` chunks drawn uniformly in the action box from each history's own stream."""
        (low, high), shape = self.config.box, (self.config.num_proposals, self.horizon, self.action_dim)
        u = torch.stack([torch.rand(shape, generator=g) for g in generators[:b]])
        return low + u * (high - low)


def _batch(obs: Mapping[str, np.ndarray]) -> int:
    return int(np.asarray(next(iter(obs.values()))).shape[0])


class Rank(Planner):
    """GPC-RANK (and V-GPS, the ceiling): the policy's K proposals, scored once."""

    def search(self, objective: Objective, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator],
               timer: PartTimer) -> Found:
        chunks = self.proposals(obs, self.config.num_proposals, generators, timer)
        scores, futures = objective(chunks)
        return chunks, scores, futures


class Opt(Planner):
    """Gradient ascent on the chunks through the scorer: GPC-OPT (one proposal), GPC-RANK+OPT (K), or from random chunks."""

    def search(self, objective: Objective, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator],
               timer: PartTimer) -> Found:
        cfg = self.config
        if cfg.uses_policy:
            start = self.proposals(obs, cfg.num_proposals, generators, timer)
        else:
            start = self.uniform(generators, _batch(obs))
        return ascend(objective, start, cfg, timer, self.trace)


class CEM(Planner):
    """Prior-free cross-entropy method: M iterations of K samples, refitted to the elites."""

    def search(self, objective: Objective, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator],
               timer: PartTimer) -> Found:
        return self.sample_search(objective, generators, _batch(obs), timer)

    def refit(self, samples: torch.Tensor, scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The next mean and std (None: keep it) from ``(B, K, T, A)`` samples and their scores."""
        n_elite = max(1, int(round(self.config.elite_fraction * self.config.num_proposals)))
        elite = samples.gather(1, scores.topk(n_elite, dim=1).indices[..., None, None].expand(-1, -1, *samples.shape[2:]))
        low, high = self.config.box
        return elite.mean(dim=1), elite.std(dim=1, unbiased=False).clamp_min(1e-3 * (high - low))

    def sample_search(self, objective: Objective, generators: Sequence[torch.Generator], b: int,
                      timer: PartTimer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """M iterations of K samples around a mean refitted by ``refit``.

        Returns the best chunk seen per history (as a K=1 candidate set) with its score and future.
        """
        cfg = self.config
        low, high = cfg.box
        span = high - low
        mean = torch.full((b, self.horizon, self.action_dim), low + span / 2)
        std = torch.full_like(mean, cfg.init_std * span)
        best_chunk, best_score, best_future = None, None, None
        for _ in range(cfg.opt_steps):
            shape = (cfg.num_proposals, self.horizon, self.action_dim)
            noise = torch.stack([torch.randn(shape, generator=g) for g in generators[:b]])
            samples = (mean[:, None] + std[:, None] * noise).clamp(low, high)
            with torch.no_grad():
                scores, futures = objective(samples)
            with timer("optimizer"):
                top = scores.argmax(dim=1)
                rows = torch.arange(b)
                if best_chunk is None or best_score is None or best_future is None:
                    best_chunk, best_score, best_future = samples[rows, top], scores[rows, top], futures[rows, top]
                else:
                    better = scores[rows, top] > best_score
                    best_chunk = torch.where(better[:, None, None], samples[rows, top], best_chunk)
                    best_future = torch.where(better.view(-1, *[1] * (futures.dim() - 2)), futures[rows, top], best_future)
                    best_score = torch.where(better, scores[rows, top], best_score)
                mean, new_std = self.refit(samples, scores)
                std = std if new_std is None else new_std
        assert best_chunk is not None and best_score is not None and best_future is not None  # opt_steps >= 1
        return best_chunk[:, None], best_score[:, None], best_future[:, None]


class MPPI(CEM):
    """Prior-free MPPI: the mean moves to the reward-weighted average of the samples (the spread stays)."""

    def refit(self, samples: torch.Tensor, scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        weights = torch.softmax((scores - scores.max(dim=1, keepdim=True).values) / self.config.temperature, dim=1)
        return (weights[..., None, None] * samples).sum(dim=1), None


def build_planner(config: PlannerConfig, scorer: Scorer, policy: ActionProposer | None = None,
                  sampling: SamplingConfig = SamplingConfig(), **timeline: Any) -> Planner:
    """The planner class ``config.kind`` registered, over ``scorer``; ``timeline``: horizon, n_action_steps and
    action_dim for a planner without a policy."""
    cls = config.planner.planner_class()
    if not (isinstance(cls, type) and issubclass(cls, Planner)):
        raise ValueError(f"planner {config.kind}: {config.planner.planner} is not a gpc.models.planning.planner.Planner")
    return cls(config, scorer, policy, sampling, **timeline)


def model_planner(config: PlannerConfig, world_model: WorldModel, reward: Reward, policy: ActionProposer | None = None,
                  sampling: SamplingConfig = SamplingConfig(), **timeline: Any) -> Planner:
    """GPC's planners (and the prior-free ones) over a world model and a reward (``ModelScorer``)."""
    return build_planner(config, ModelScorer(world_model, reward), policy, sampling, **timeline)
