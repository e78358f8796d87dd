"""Planners by name, as tasks are: what each needs and does, so configs, recipes and commands never list them.

A planner is a class (``gpc.models.planning.planner.Planner`` or one of yours) that scores
candidate chunks with a *scorer* built from one checkpoint (``--world-model CKPT``): GPC's
planners and the prior-free baselines roll a world model out and score the futures with the
task's reward; V-GPS ranks with a Q-function (``gpc.models.values``); a latent-model ranker
with its own imagined reward. ``PlannerKind`` says which, and the harness does the rest
(loading, pairing checks, results identity). Yours becomes known in one of two ways:

- ``register_planner(PlannerKind(...))`` in your process (worker processes import the same module);
- ``GPC_PLANNERS=my_package.my_module:KIND`` (comma-separated for several) in the environment.

Classes and loaders are named ``module:attr`` and imported on first use, so this module (and a
config naming a planner) imports no network code.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from gpc.models.named import load_named

ENV_VAR = "GPC_PLANNERS"
WORLD_MODEL = "gpc.harness.recipes:load_world_model"  # the loader of GPC's scorers: a world model (or gt-sim) + the reward


@dataclass(frozen=True)
class PlannerKind:
    """One planner: its class, how its checkpoint loads, and what it asks of the policy and the search."""

    name: str  # --planner NAME
    planner: str  # "module:Class", a Planner subclass (its search)
    load: str = WORLD_MODEL  # "module:function" (path, task, device) -> the model the scorer wraps
    model: str = "world model"  # what --world-model names for it, in messages
    uses_policy: bool = True  # starts from the policy's proposals (False: random chunks in the action box)
    uses_gradients: bool = False  # differentiates the score with respect to the actions
    iterates: bool = False  # takes M steps (gradient steps or sampling iterations)
    single: bool = False  # refines one proposal (K is 1)
    uses_reward: bool = True  # its scorer reads the task's reward (--reward); a value function has its own
    description: str = ""  # one line for --help

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"planner name {self.name!r}: use letters, digits, - and _")
        for field_name in ("planner", "load"):
            if ":" not in getattr(self, field_name):
                raise ValueError(f"planner {self.name}: {field_name} {getattr(self, field_name)!r} is not 'module:attr'")

    @property
    def prior_free(self) -> bool:
        return not self.uses_policy

    def planner_class(self) -> Any:
        return load_named(self.planner, f"planner {self.name}")

    def loader(self) -> Any:
        return load_named(self.load, f"planner {self.name}")


_PLANNER = "gpc.models.planning.planner"
_VALUE = "gpc.models.values.module:load_value"
BUILT_IN = (
    PlannerKind("rank", f"{_PLANNER}:Rank", description="GPC-RANK: the best of K proposals by predicted reward"),
    PlannerKind("opt", f"{_PLANNER}:Opt", uses_gradients=True, iterates=True, single=True,
                description="GPC-OPT: one proposal refined by M gradient steps"),
    PlannerKind("rank-opt", f"{_PLANNER}:Opt", uses_gradients=True, iterates=True,
                description="GPC-RANK+OPT: K proposals refined, the best kept"),
    PlannerKind("cem", f"{_PLANNER}:CEM", uses_policy=False, iterates=True, description="prior-free cross-entropy method"),
    PlannerKind("mppi", f"{_PLANNER}:MPPI", uses_policy=False, iterates=True, description="prior-free MPPI"),
    PlannerKind("grad", f"{_PLANNER}:Opt", uses_policy=False, uses_gradients=True, iterates=True,
                description="prior-free gradient ascent from random chunks"),
    PlannerKind("vgps", f"{_PLANNER}:Rank", load=_VALUE, model="value function", uses_reward=False,
                description="V-GPS: the best of K proposals by an offline Q-function (gpc train value)"),
    PlannerKind("dreamer", f"{_PLANNER}:Rank", load="gpc.models.latent.module:load_latent", model="latent world model",
                uses_reward=False, description="DreamerV3-style: the best of K proposals by the reward an RSSM imagines "
                "(gpc train latent-world-model)"),
    PlannerKind("ladi", f"{_PLANNER}:Rank", load="gpc.models.ladi.module:load_ladi", model="latent diffusion world model",
                uses_reward=False, description="LaDi-WM-style: the best of K proposals by the reward of latents a diffusion "
                "model predicts (gpc train latent-world-model --kind ladi)"),
)
_REGISTRY: dict[str, PlannerKind] = {kind.name: kind for kind in BUILT_IN}
_discovered: list[bool] = []


def register_planner(kind: PlannerKind) -> PlannerKind:
    """Make ``kind`` known by its name (replacing an earlier registration of that name)."""
    _REGISTRY[kind.name] = kind
    return kind


def _discover() -> None:
    if _discovered:
        return
    _discovered.append(True)
    for spec in filter(None, os.environ.get(ENV_VAR, "").split(",")):
        kind = load_named(spec if ":" in spec else f"{spec}:KIND", f"${ENV_VAR}")
        if not isinstance(kind, PlannerKind):
            raise ValueError(f"${ENV_VAR}: {spec!r} is a {type(kind).__name__}, not a PlannerKind")
        _REGISTRY.setdefault(kind.name, kind)


def planner_names() -> tuple[str, ...]:
    _discover()
    return tuple(_REGISTRY)


def planner_kind(name: str) -> PlannerKind:
    if name not in _REGISTRY:
        _discover()
    if name not in _REGISTRY:
        raise ValueError(f"--planner {name!r}: use one of {', '.join(planner_names())} "
                         f"(name your own in ${ENV_VAR}=module:KIND or register it with register_planner)")
    return _REGISTRY[name]

