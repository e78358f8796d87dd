"""The behaviour-cloning controller: the frozen policy's own proposal, executed as Diffusion Policy does."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from gpc.models.planning.config import SamplingConfig
from gpc.models.planning.protocols import Plan
from gpc.models.policy.module import PolicyModule


class PolicyController:
    """GPC's K=1, M=0 case: sample one chunk per history and execute its first actions."""

    def __init__(self, policy: PolicyModule, sampling: SamplingConfig = SamplingConfig()) -> None:
        self.policy = policy
        self.sampling = sampling
        self.obs_keys = policy.obs_keys
        self.n_obs_steps = policy.config.n_obs_steps

    def plan(self, obs: Mapping[str, np.ndarray], generators: Sequence[torch.Generator]) -> Plan:
        t0 = time.perf_counter()
        batch = {k: torch.as_tensor(obs[k]) for k in self.obs_keys}
        chunk = self.sampling.sample(self.policy, batch, 1, generators)[:, 0].cpu().numpy()
        now = chunk[:, self.policy.action_slice.start :]  # the chunk from the current step on
        return Plan(actions=now[:, : self.policy.config.n_action_steps], chunk=now,
                    seconds={"policy": time.perf_counter() - t0})
