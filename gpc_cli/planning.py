"""Controllers from checkpoints: the recipe `gpc eval --planner` and `gpc plan` build in every worker.

It joins what ``models`` cannot know (the task's reward geometry, action box and simulator)
with the checkpoints, and checks that policy and world model belong together.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from datasets.errors import DataError
from models.controllers import PolicyController, SamplingConfig
from models.planner_config import PlannerConfig
from models.protocols import Controller
from tasks import get_task

GT_SIM = "gt-sim"
REWARDS = ("registration", "learned", "vlm")
IMAGE_FAMILY = ("image",)


@dataclass(frozen=True)
class RewardSpec:
    """Which reward scores the predicted futures."""

    kind: str = "registration"  # registration (state futures) | learned (image futures) | vlm (selects)
    aggregate: str = "final"  # final | discounted
    checkpoint: str | None = None  # learned: the reward checkpoint
    vlm: Any = None  # vlm: a models.vlm_reward.VLMConfig

    def __post_init__(self) -> None:
        if self.kind not in REWARDS:
            raise ValueError(f"--reward {self.kind!r}: use one of {', '.join(REWARDS)}")
        if self.kind == "learned" and not self.checkpoint:
            raise ValueError("--reward learned needs --reward-checkpoint (train one with `gpc train reward`)")
        if self.kind == "vlm" and self.vlm is None:
            raise ValueError("--reward vlm needs --vlm-base-url and --vlm-model")


def load_world_model(path: str, task: str) -> Any:
    """The ground-truth simulator for ``gt-sim``, else a world-model checkpoint of ``task`` (state or image)."""
    if path == GT_SIM:
        return get_task(task).SimulatorModel()
    from models.planners import load_world_model as load

    return load(path, task)


def build_reward(spec: RewardSpec, task: str) -> Any:
    """The task's registration reward (its T's corners and default goal), or a learned / VLM one."""
    from models.reward import RegistrationReward, RewardConfig

    t = get_task(task)
    config = RewardConfig(aggregate=spec.aggregate)
    registration = RegistrationReward(torch.as_tensor(t.REWARD_VERTICES), torch.as_tensor(t.DEFAULT_GOAL), config)
    if spec.kind == "registration":
        return registration
    if spec.kind == "learned":
        from models.reward_predictor import ImageReward

        return ImageReward.from_checkpoint(spec.checkpoint, torch.as_tensor(t.DEFAULT_GOAL), config, task=task)
    from models.vlm_reward import VLMReward

    return VLMReward(spec.vlm, render=t.render_future, fallback=registration, task_description=t.TASK_DESCRIPTION)


def check_pairing(policy: Any, world_model: Any, path: str) -> None:
    """A world model must predict the task the policy acts in, from observations the policy's setting has."""
    if path == GT_SIM:
        return
    wm_task = world_model.config.task
    if wm_task != policy.config.task:
        raise DataError(f"{path}: world model for task {wm_task!r}, but the policy acts in {policy.config.task!r}")
    wm_image = getattr(world_model, "obs_key", "state") == "img"
    if wm_image != (policy.config.obs_type in IMAGE_FAMILY):
        raise DataError(
            f"{path}: a {'visual' if wm_image else 'state'} world model cannot plan for a {policy.config.obs_type} "
            f"policy (pair state/keypoints policies with state world models, image policies with visual ones)"
        )


@dataclass(frozen=True)
class PlannerRecipe:
    """Picklable recipe for a controller: BC when ``planner`` is None, else a planner over a world model."""

    policy: str
    planner: PlannerConfig | None = None
    world_model: str | None = None  # checkpoint, or "gt-sim"
    reward: RewardSpec = field(default_factory=RewardSpec)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    task: str | None = None

    def __post_init__(self) -> None:
        if self.planner is not None and not self.world_model:
            raise ValueError(f"--planner {self.planner.kind} needs --world-model CKPT (or --world-model {GT_SIM})")
        if self.world_model == GT_SIM and self.planner is not None and self.planner.uses_gradients:
            raise ValueError(f"--planner {self.planner.kind} differentiates through the world model; {GT_SIM} is not differentiable")

    @property
    def label(self) -> str:
        if self.planner is None:
            return "bc"
        name = self.planner.label
        return name.replace("rank", GT_SIM, 1) if self.world_model == GT_SIM else name

    def __call__(self) -> Controller:
        from models.planners import Planner
        from models.policy import PolicyModule

        policy = PolicyModule.load_from_checkpoint(self.policy, task=self.task)
        if self.planner is None:
            return PolicyController(policy, self.sampling)
        task = policy.config.task
        world_model = load_world_model(self.world_model, task)
        check_pairing(policy, world_model, self.world_model)
        t = get_task(task)
        import dataclasses

        config = dataclasses.replace(self.planner, action_low=t.ACTION_LOW, action_high=t.ACTION_HIGH)
        return Planner(config, world_model, build_reward(self.reward, task), policy, self.sampling)


def planner_summary(recipe: PlannerRecipe) -> dict[str, Any]:
    """What a results file records about the controller."""
    out: dict[str, Any] = {"controller": recipe.label, "policy": recipe.policy}
    if recipe.planner is not None:
        out.update(planner=dict(vars(recipe.planner)), world_model=recipe.world_model, reward=recipe.reward.kind)
    return out
