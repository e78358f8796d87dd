"""Planners from checkpoints: the pairing check and deployment on your own robot loop.

A world model must predict the task the policy acts in, from observations the policy's
setting has: state and keypoint policies pair with state world models, image policies with
visual ones. ``load_planner`` checks that before it returns a controller.
"""

from __future__ import annotations

import os
from typing import Any

from gpc.datasets.errors import DataError
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.planner import Planner, model_planner
from gpc.models.planning.protocols import Reward, WorldModel
from gpc.models.policy.formats import ForeignTask, feature_sources, load_policy
from gpc.models.policy.module import PolicyModule
from gpc.models.world_models.ensemble import load_any

IMAGE_KEY = "img"
IMAGE_POLICIES = ("image",)


def check_pairing(policy: PolicyModule, world_model: Any, source: str) -> None:
    """Refuse a world model of another task, or of the other observation family, than the policy's.

    A model without a gpc config (the ground-truth simulator, your own) is taken as it is.
    """
    config = getattr(world_model, "config", None)
    if config is None or not hasattr(config, "task"):
        return
    if config.task != policy.config.task:
        raise DataError(f"{source}: world model for task {config.task!r}, but the policy acts in {policy.config.task!r}")
    visual = getattr(world_model, "obs_key", "state") == IMAGE_KEY
    if visual != (policy.config.obs_type in IMAGE_POLICIES):
        raise DataError(
            f"{source}: a {'visual' if visual else 'state'} world model cannot plan for a {policy.config.obs_type} "
            "policy (pair state/keypoints policies with state world models, image policies with visual ones)"
        )


def load_planner(policy: str | os.PathLike | PolicyModule, world_model: str | os.PathLike | WorldModel, reward: Reward,
                 config: PlannerConfig = PlannerConfig(), sampling: SamplingConfig = SamplingConfig(),
                 task: ForeignTask | None = None, policy_format: str | None = None) -> Planner:
    """Deployment: a policy and a world model (checkpoints or objects) + a reward -> a controller with ``act(obs_history)``.

    ``policy`` may be a gpc checkpoint, a LeRobot policy directory or a Diffusion Policy ``.ckpt``
    (``policy_format``: detected when None); a foreign one needs the ``task`` it acts in
    (``gpc.tasks.get_task(name)``), whose keys it then reads (``planner.obs_keys`` lists them).
    No simulator is involved; give ``config.action_low/high`` your robot's action box.
    """
    if isinstance(policy, PolicyModule):
        proposer = policy
    else:
        sources = feature_sources(task) if task is not None else None
        proposer = load_policy(policy, sources, task.name if task is not None else None, policy_format)
    model: WorldModel
    if isinstance(world_model, (str, os.PathLike)):
        source, model = str(world_model), load_any(world_model)
    else:
        source, model = type(world_model).__name__, world_model
    check_pairing(proposer, model, source)
    return model_planner(config, model, reward, proposer, sampling)
