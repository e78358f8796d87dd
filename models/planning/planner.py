"""GPC's planners and the prior-free baselines, as one controller over the three protocols.

A decision for B observation histories (lockstep episodes) works on ``B * K`` candidate
chunks at once: the policy proposes ``(B, K, T, A)`` chunks in one batched call, the world
model rolls all ``B * K`` out in one call, the reward scores them in one call, and each
history executes its best candidate. Gradient steps (GPC-OPT, RANK+OPT, prior-free ``grad``)
update all candidates together; Adam acts per entry and every candidate's reward depends on
its own chunk only, so optimising K chunks as one batch equals optimising them one by one.

Chunks here run from the current step on (``T = horizon - n_obs_steps + 1`` actions); the
world model predicts the state after each of them, and the reward scores those futures.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from gpc.models.planning.ascent import AscentTrace, ascend
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.objective import GOAL_KEY, Objective, PartTimer
from gpc.models.planning.protocols import ActionProposer, Plan, Reward, WorldModel


class Planner:
    """A ``Controller``: GPC-RANK / OPT / RANK+OPT on the policy's proposals, or CEM / MPPI / grad without them.

    ``world_model.obs_key`` (default ``state``) names the observation the world model reads;
    an observation ``goal`` (tasks with a per-episode goal) is passed to the reward. The world
    model's and reward's weights are frozen here (``requires_grad_(False)``): ascent moves actions only.
    """

    def __init__(self, config: PlannerConfig, world_model: WorldModel, reward: Reward,
                 policy: ActionProposer | None = None, sampling: SamplingConfig = SamplingConfig(),
                 horizon: int | None = None, n_action_steps: int | None = None, action_dim: int | None = None) -> None:
        if config.uses_policy and policy is None:
            raise ValueError(f"planner {config.kind} needs a policy checkpoint")
        if config.uses_gradients and getattr(reward, "selects", False):
            raise ValueError(f"planner {config.kind} needs a differentiable reward; a selecting reward only ranks")
        self.config, self.world_model, self.reward, self.policy, self.sampling = config, world_model, reward, policy, sampling
        for frozen in (world_model, reward):  # ascent differentiates the actions only: no gradients for the weights
            if isinstance(frozen, torch.nn.Module):
                frozen.requires_grad_(False)
        self.wm_key = getattr(world_model, "obs_key", "state")
        if policy is not None:
            pc = policy.config
            self.now = pc.n_obs_steps - 1  # index of the current step in a policy chunk
            self.horizon = pc.horizon - self.now
            self.n_action_steps = config.action_steps or pc.n_action_steps
            self.obs_keys = tuple(dict.fromkeys(policy.obs_keys + (self.wm_key,)))
            self.n_obs_steps = max(pc.n_obs_steps, world_model.n_obs_steps)
            self.action_dim = pc.action_dim
        else:
            if horizon is None or n_action_steps is None or action_dim is None:
                raise ValueError("a planner without a policy needs horizon, n_action_steps and action_dim")
            self.now, self.horizon, self.action_dim = 0, horizon, action_dim
            self.n_action_steps = config.action_steps or n_action_steps
            self.obs_keys, self.n_obs_steps = (self.wm_key,), world_model.n_obs_steps
        if not 1 <= self.n_action_steps <= self.horizon:
            raise ValueError(f"--action-steps {self.n_action_steps}: must lie in 1..{self.horizon} (the actions a chunk plans)")
        if config.knots > self.horizon:
            raise ValueError(f"--knots {config.knots}: at most {self.horizon}, the actions a chunk plans")
        self.episodes: Sequence[int] | None = None
        self.trace: AscentTrace | None = None  # set one to record the next decisions' gradient ascent (diagnostics)

    def start(self, episodes: Sequence[int]) -> None:
        """The harness names the episodes (seeds) of the next decisions' histories: the lockstep group's before
        its first decision, the unfinished ones whenever some finish."""
        self.episodes = list(episodes)

    def stats(self) -> dict[str, Any]:
        """Counters of the reward (a VLM's queries and fallbacks), summed over every decision so far."""
        stats = getattr(self.reward, "stats", None)
        return dict(stats() if callable(stats) else stats or {})

    # ------------------------------------------------------------------ the decision
    def plan(self, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator]) -> Plan:
        timer, cfg = PartTimer(), self.config
        history = torch.as_tensor(np.asarray(obs[self.wm_key]))
        goal = torch.as_tensor(np.asarray(obs[GOAL_KEY])[:, -1], dtype=torch.float32) if GOAL_KEY in obs else None
        objective = Objective(self.world_model, self.reward, history, goal, timer, self.episodes)
        if cfg.uses_policy:
            assert self.policy is not None  # __init__ refuses a policy planner without one
            with timer("policy"):
                k = 1 if cfg.kind == "opt" else cfg.num_proposals
                chunks = self.sampling.sample(self.policy, obs, k, generators)[:, :, self.now :].float()
            if cfg.kind == "rank":
                scores, futures = objective(chunks)
            else:
                chunks, scores, futures = ascend(objective, chunks, cfg, timer, self.trace)
        elif cfg.kind == "grad":
            chunks, scores, futures = ascend(objective, self.uniform(generators, history.shape[0]), cfg, timer, self.trace)
        else:
            chunks, scores, futures = self.sample_search(objective, generators, history.shape[0], timer)
        best = scores.argmax(dim=1)
        rows = torch.arange(chunks.shape[0])
        chunk = chunks[rows, best].detach().cpu().numpy()
        return Plan(
            actions=chunk[:, : self.n_action_steps], chunk=chunk, seconds=timer.seconds,
            scores=scores.detach().cpu().numpy(), chosen=best.cpu().numpy(),
            futures=futures.detach().cpu().numpy() if cfg.keep_futures else None,
            candidates=chunks.detach().cpu().numpy() if cfg.keep_futures else None,
        )

    def act(self, obs_history: Mapping[str, Any], generator: torch.Generator | None = None) -> np.ndarray:
        """Deployment: ``{key: (H, ...)}`` one raw observation history -> ``(T, A)`` chunk from now on."""
        batched = {k: np.asarray(v)[None] for k, v in obs_history.items()}
        with torch.no_grad():
            return self.plan(batched, [generator if generator is not None else torch.Generator()]).chunk[0]

    # ------------------------------------------------------------------ searches
    def uniform(self, generators: Sequence[torch.Generator], b: int) -> torch.Tensor:
        """``(B, K, T, A)`` chunks drawn uniformly in the action box from each history's own stream."""
        (low, high), shape = self.config.box, (self.config.num_proposals, self.horizon, self.action_dim)
        u = torch.stack([torch.rand(shape, generator=g) for g in generators[:b]])
        return low + u * (high - low)

    def sample_search(self, objective: Objective, generators: Sequence[torch.Generator], b: int,
                      timer: PartTimer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """CEM (refit to the elites) or MPPI (reward-weighted mean) over M iterations of K samples.

        Returns the best chunk seen per history (as a K=1 candidate set) with its score and future.
        """
        cfg = self.config
        low, high = cfg.box
        span = high - low
        mean = torch.full((b, self.horizon, self.action_dim), low + span / 2)
        std = torch.full_like(mean, cfg.init_std * span)
        best_chunk, best_score, best_future = None, None, None
        n_elite = max(1, int(round(cfg.elite_fraction * cfg.num_proposals)))
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
                if cfg.kind == "cem":
                    elite = samples.gather(1, scores.topk(n_elite, dim=1).indices[..., None, None].expand(-1, -1, *shape[1:]))
                    mean, std = elite.mean(dim=1), elite.std(dim=1, unbiased=False).clamp_min(1e-3 * span)
                else:
                    weights = torch.softmax((scores - scores.max(dim=1, keepdim=True).values) / cfg.temperature, dim=1)
                    mean = (weights[..., None, None] * samples).sum(dim=1)
        assert best_chunk is not None and best_score is not None and best_future is not None  # opt_steps >= 1
        return best_chunk[:, None], best_score[:, None], best_future[:, None]
