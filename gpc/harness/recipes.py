"""Controllers from checkpoints: the recipe closed-loop evaluation builds in every worker process.

It joins what ``gpc.models`` cannot know (the task's reward geometry, action box and
simulator) with the checkpoints, and checks that policy and world model belong together
(``gpc.models.planning.loading.check_pairing``). ``make_recipe`` is what ``gpc eval`` and
``gpc plan`` call with their options; ``PlannerRecipe`` is picklable, so worker processes
load the checkpoints themselves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError
from gpc.models.networks.precision import check_rollout_precision
from gpc.models.planning.config import PlannerConfig, SamplingConfig
from gpc.models.planning.protocols import Controller
from gpc.models.planning.registry import WORLD_MODEL, planner_kind, planner_names
from gpc.models.policy.controller import PolicyController
from gpc.models.rewards.registration import AGGREGATES
from gpc.tasks import get_task
from gpc.tasks.base import Task

GT_SIM = "gt-sim"
BC = "bc"
REWARDS = ("registration", "learned", "vlm")
ASCENT_DEFAULTS = {f.name: f.default for f in dataclasses.fields(PlannerConfig)
                   if f.name in ("lr_decay", "trust_region", "keep_best", "knots")}
# Settings added after results were first written: left out of a summary at their default, so those results resume.
LATER_DEFAULTS = {"action_steps": None, "knots": 0}
# The VLM settings that change its answers (not where it is served, its key, time-outs or cache), each left out at its default.
VLM_IDENTITY = ("model", "temperature", "prompt", "frame_size", "columns", "max_tokens")
# The gradient planners' Adam step when --lr is not given: Push-T's 2 px of its 512 px action box, as a share of the
# task's box, so a task in metres (Block Stacking's 0.4 m box: 1.6 mm) moves its actions as far, relative to their
# range, as Push-T does (2 px on every 512 px planar task: their figures unchanged).
DEFAULT_LR_SHARE = 2.0 / 512
DEFAULT_STEPS = {"cem": 5, "mppi": 5}  # M when not given: 30 for the gradient planners, 0 for those that take no steps
DEVICES = ("cpu", "cuda")  # where the controller's networks run (--device)


def planner_choices() -> tuple[str, ...]:
    """Every --planner value: the policy alone, GPC's planners, the ground-truth ceiling, then the other registered ones."""
    names = planner_names()
    return (BC, *names[:3], GT_SIM, *names[3:])


@dataclass(frozen=True)
class RewardSpec:
    """Which reward scores the predicted futures."""

    kind: str = "registration"  # registration: the task's state reward (state futures) | learned (image futures) | vlm (selects)
    aggregate: str = "final"  # final | discounted
    checkpoint: str | None = None  # learned: the reward checkpoint
    vlm: Any = None  # vlm: a gpc.models.rewards.vlm.VLMConfig

    def __post_init__(self) -> None:
        if self.kind not in REWARDS:
            raise ValueError(f"--reward {self.kind!r}: use one of {', '.join(REWARDS)}")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"--reward-aggregate {self.aggregate!r}: use one of {', '.join(AGGREGATES)}")
        if self.kind == "learned" and not self.checkpoint:
            raise ValueError("--reward learned needs --reward-checkpoint (train one with `gpc train reward`)")
        if self.kind == "vlm" and self.vlm is None:
            raise ValueError("--reward vlm needs --vlm-base-url and --vlm-model")


def load_world_model(path: str, task: Task, device: str = "cpu") -> Any:
    """The task's ground-truth simulator for ``gt-sim``, else a world-model checkpoint of the task (state or image, one
    model or an ensemble) on ``device``."""
    if path == GT_SIM:
        return task.simulator()
    from gpc.models.world_models.ensemble import load_any

    return load_any(path, task.name, map_location=device).to(device)


def build_reward(spec: RewardSpec, task: Task, device: str = "cpu") -> Any:
    """The task's own reward on predicted states (``Task.state_reward``: Push-T's registration of its objects), or a
    learned / VLM one (the state reward is the VLM's fallback)."""
    from gpc.models.rewards.registration import RewardConfig
    from gpc.models.rewards.state import state_reward

    config = RewardConfig(aggregate=spec.aggregate)
    registration = state_reward(task.state_reward, task.layout, config)
    if spec.kind == "registration":
        return _on(registration, device)
    if spec.kind == "learned":
        from gpc.models.rewards.image_state import learned_image_reward

        assert spec.checkpoint is not None  # RewardSpec refuses a learned reward without one
        return learned_image_reward(spec.checkpoint, registration, task.layout.goal, config, map_location=device,
                                    task=task.name).to(device)
    from gpc.models.rewards.vlm import VLMReward

    return VLMReward(spec.vlm, render=task.render_state, fallback=registration, task_description=task.description)


@dataclass(frozen=True)
class PlannerRecipe:
    """Picklable recipe for a controller: BC when ``planner`` is None, else a planner over a world model."""

    policy: str
    planner: PlannerConfig | None = None
    world_model: str | None = None  # checkpoint, or "gt-sim"
    reward: RewardSpec = field(default_factory=RewardSpec)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    task: str | None = None
    policy_format: str | None = None  # gpc | lerobot | diffusion_policy (None: detected)
    precision: str = "bf16-auto"  # the world model's rollouts (networks.precision.ROLLOUT_PRECISIONS)
    rollouts: str = "float32"  # the dtype they run in here, as make_recipe found it: results record it (bf16 changes the numbers)
    device: str = "cpu"  # where the networks load and run (DEVICES)

    def __post_init__(self) -> None:
        check_rollout_precision(self.precision)
        if self.device not in DEVICES:
            raise ValueError(f"--device {self.device!r}: use one of {', '.join(DEVICES)}")
        if self.planner is None:
            return
        kind = self.planner.planner
        if not self.world_model:
            also = f" (or --world-model {GT_SIM})" if kind.load == WORLD_MODEL else ""
            raise ValueError(f"--planner {kind.name} needs --world-model CKPT, its {kind.model}{also}")
        if self.world_model == GT_SIM and kind.load != WORLD_MODEL:
            raise ValueError(f"--planner {kind.name} scores with a {kind.model}, not the simulator; drop --world-model {GT_SIM}")
        if self.world_model == GT_SIM and kind.uses_gradients:
            raise ValueError(f"--planner {kind.name} differentiates through the world model; {GT_SIM} is not differentiable")

    @property
    def label(self) -> str:
        """``bc``, ``rank K=100``, ...; a sampler other than the checkpoint's own is named: ``bc [ddpm 100 steps]``."""
        if self.planner is None:
            name = BC
        else:
            name = self.planner.label
            name = name.replace("rank", GT_SIM, 1) if self.world_model == GT_SIM else name
        sampler = self.sampler()
        words = [sampler.get("method"), f"{sampler['steps']} steps" if "steps" in sampler else None, sampler.get("spacing")]
        return f"{name} [{' '.join(w for w in words if w)}]" if sampler else name

    def sampler(self) -> dict[str, Any]:
        """The policy's sampler settings that are not the checkpoint's own (``make_recipe`` leaves those out)."""
        return {key: value for key, value in dataclasses.asdict(self.sampling).items() if value is not None}

    def __call__(self) -> Controller:
        from gpc.harness.policies import load_policy
        from gpc.models.planning.loading import check_pairing
        from gpc.models.planning.objective import ModelScorer
        from gpc.models.planning.planner import build_planner

        policy = load_policy(self.policy, self.task, self.policy_format, map_location=self.device).to(self.device)
        if self.planner is None:
            return PolicyController(policy, self.sampling)
        assert self.world_model is not None
        task = get_task(policy.config.task)
        kind = self.planner.planner
        model = kind.loader()(self.world_model, task, self.device)  # a world model (GPC's), a value function, ...
        check_pairing(policy, model, self.world_model)
        if hasattr(model, "set_rollout_precision"):  # the simulator (gt-sim) and value functions have none
            model.set_rollout_precision(self.precision)
        box = task.layout.action
        config = dataclasses.replace(self.planner, action_low=box.low, action_high=box.high)
        scorer = ModelScorer(model, build_reward(self.reward, task, self.device)) if kind.uses_reward else model
        return build_planner(config, scorer, policy, self.sampling)

    def summary(self) -> dict[str, Any]:
        """What a results file records about the controller: every setting its numbers depend on
        (``gpc.harness.identity``), those added later left out at their defaults."""
        out: dict[str, Any] = {"controller": self.label, "policy": self.policy}
        if self.device != "cpu":  # left out on the CPU, where every result before this setting ran
            out["device"] = self.device
        if self.policy_format not in (None, "gpc"):
            out["policy_format"] = self.policy_format
        if self.sampler():
            out["sampling"] = self.sampler()
        if self.planner is not None:
            planner = {key: value for key, value in dataclasses.asdict(self.planner).items()
                       if key not in LATER_DEFAULTS or value != LATER_DEFAULTS[key]}
            out.update(planner=planner, world_model=self.world_model)
            if self.planner.planner.uses_reward:  # (a value function scores with its own)
                out["reward"] = self.reward.kind
            if self.reward.aggregate != "final":
                out["reward_aggregate"] = self.reward.aggregate
            if self.reward.vlm is not None:
                defaults = type(self.reward.vlm)()
                out["vlm"] = {key: getattr(self.reward.vlm, key) for key in VLM_IDENTITY
                              if getattr(self.reward.vlm, key) != getattr(defaults, key)}
            if self.rollouts != "float32":  # left out at float32, which every result before this setting used
                out["rollouts"] = self.rollouts
        return out


def make_recipe(policy: str | Path, planner: str = BC, *, world_model: str | None = None, k: int | None = None,
                m: int | None = None, lr: float | None = None, ascent: Mapping[str, Any] | None = None, reward: RewardSpec = RewardSpec(),
                sampling: SamplingConfig = SamplingConfig(), goal: str = "fixed", keep_futures: bool = False,
                task: str | None = None, policy_format: str | None = None, action_steps: int | None = None,
                precision: str = "bf16-auto", device: str = "cpu") -> PlannerRecipe:
    """The controller a command line describes: ``planner`` is ``bc``, ``gt-sim`` or a ``PlannerConfig`` kind.

    ``policy`` is a gpc checkpoint, a LeRobot policy directory or a Diffusion Policy ``.ckpt``
    (``policy_format``: detected when None); a foreign one acts in ``task`` (default: the built-in one).
    ``lr``: the gradient planners' Adam step in action units (None: ``DEFAULT_LR_SHARE`` of the task's action range).
    ``ascent``: the gradient planners' guards (``PlannerConfig``'s ``lr_decay``, ``trust_region``, ``keep_best``,
    ``knots``). ``precision``: the world model's rollouts (``bf16-auto``, ``32-true``, ``bf16-mixed``).
    ``device``: where the networks run (``cpu``, ``cuda``); checked here on the CPU when this machine has no GPU
    (a Ray cluster's workers may have them).
    The checkpoints are opened and the controller built once here, so a mismatched world model,
    reward or goal mode fails now, in one line, before any episode runs.
    """
    from gpc.harness.policies import load_policy
    from gpc.models.policy.formats import detect_format

    if planner not in planner_choices():
        raise ValueError(f"--planner {planner!r}: use one of {', '.join(planner_choices())}")
    policy_format = policy_format or detect_format(policy)
    loaded = load_policy(policy, task, policy_format)
    chosen = get_task(loaded.config.task)
    chosen.check_goal(goal)
    levels = loaded.config.noise.train_steps
    if sampling.steps is not None and sampling.steps > levels:
        raise ValueError(f"--steps {sampling.steps}: the policy was trained with {levels} noise levels; use at most {levels}")
    own = loaded.config.sampler  # a setting given as the checkpoint's own is no setting: the same numbers, the same run
    sampling = SamplingConfig(*(None if getattr(sampling, key) == getattr(own, key) else getattr(sampling, key)
                                for key in ("method", "steps", "spacing")))
    unseen = [key for key in loaded.obs_keys if key not in chosen.observed_keys(True, goal)]
    if unseen:
        raise DataError(f"{policy}: the policy reads {', '.join(unseen)}, which --goal {goal} episodes do not "
                        f"observe (a policy trained with --goal random needs --goal random)")
    for key, shape in loaded.config.encoder.obs_shapes:
        want = chosen.row_shape(key)
        if want is not None and tuple(shape) != want:
            raise DataError(f"{policy}: the policy was trained on {key} rows of {tuple(shape)}; task {chosen.name} observes {want}")
    gradients = tuple(name for name in planner_names() if planner_kind(name).uses_gradients)
    if {key: value for key, value in (ascent or {}).items() if ASCENT_DEFAULTS[key] != value} and planner not in gradients:
        raise ValueError(f"--lr-decay, --trust-region, --keep-best and --knots apply to {', '.join(gradients)}, "
                         f"not --planner {planner}")
    if planner == BC:
        if world_model or k or m or action_steps:
            raise ValueError("--world-model, --K, --M and --action-steps apply to a --planner (bc is the policy alone)")
        return PlannerRecipe(str(policy), sampling=sampling, task=chosen.name, policy_format=policy_format, precision=precision,
                             device=device)
    kind = "rank" if planner == GT_SIM else planner
    if planner == GT_SIM:
        if world_model not in (None, GT_SIM):
            raise ValueError(f"--planner {GT_SIM} uses the true simulator; drop --world-model {world_model}")
        world_model = GT_SIM
    box, registered = chosen.layout.action, planner_kind(kind)
    steps = DEFAULT_STEPS.get(kind, 30) if registered.iterates else 0
    config = PlannerConfig(kind=kind, num_proposals=k if k is not None else (1 if registered.single else 100),
                           opt_steps=m if m is not None else steps,
                           lr=lr if lr is not None else DEFAULT_LR_SHARE * (box.high - box.low), action_low=box.low, action_high=box.high,
                           keep_futures=keep_futures and registered.load == WORLD_MODEL,  # futures to draw: a model's
                           action_steps=action_steps, **(ascent or {}))

    recipe = PlannerRecipe(str(policy), config, world_model, reward, sampling, chosen.name, policy_format, precision, device=device)
    here = device if device == "cpu" or _cuda() else "cpu"
    controller = dataclasses.replace(recipe, device=here)()  # built once here: a mismatched world model or reward fails now, in one line
    set_precision = getattr(getattr(controller, "world_model", None), "set_rollout_precision", None)  # not BC's, nor gt-sim's
    rollouts = set_precision(precision) if set_precision is not None else "float32"
    return dataclasses.replace(recipe, rollouts=rollouts)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def _on(reward: Any, device: str) -> Any:
    """A reward that is a torch module (its vertices and goal) moved to ``device``; any other as it is."""
    import torch

    return reward.to(device) if isinstance(reward, torch.nn.Module) else reward
