"""A closed-loop run's identity: every setting its numbers depend on, defined here once.

``gpc eval --resume`` continues only a run of the same identity, ``gpc compare`` pairs and joins runs
by it, and a ``gpc record`` store records its controller's part as its provenance (resuming
appends only episodes of the same controller). The identity is

- the episodes: task, goal mode, seeds, steps per episode, sampling seed, lockstep batch, torch
  threads (``EvalConfig`` less what the scores do not depend on, ``NOT_IDENTITY``);
- the controller (``PlannerRecipe.summary``): policy, its sampler where it is not the checkpoint's own
  (method, steps, timestep spacing), planner settings, world model, reward kind and aggregate, the
  VLM's model, prompt and sampling (not its address, key or time-outs), the rollouts' dtype;
- the checkpoints' contents (SHA-256): a retrained policy, world model or reward is another run.

A setting added after results were first written is left out at its default (``recipes.LATER_DEFAULTS``,
the sampler at the checkpoint's own, the aggregate ``final``), so those results keep their identity.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gpc.harness.ownership import digest_file
from gpc.models.training.config_io import first_difference as plain_difference

if TYPE_CHECKING:  # `gpc compare` reads identities without importing torch
    from gpc.harness.evaluation import EvalConfig
    from gpc.harness.recipes import PlannerRecipe

NOT_IDENTITY = ("workers", "video_dir", "videos", "video_size", "backend")  # settings the scores do not depend on
# What makes two runs' episodes the same episodes, so that they pair seed by seed (summary field, its option);
# the rest of the identity is the controller's (another controller is another row of a comparison).
EPISODE_SETTINGS = (("task", "task"), ("goal", "--goal"), ("max_steps", "--max-steps"), ("sampling_seed", "--sampling-seeds"),
                    ("n_action_steps", "actions executed per decision"))


def controller_identity(recipe: PlannerRecipe) -> dict[str, Any]:
    """The controller's part of the identity: its settings and its checkpoints' contents (JSON types)."""
    from gpc.harness.recipes import GT_SIM  # (loaded with the recipe already)

    controller = recipe.summary()
    controller.get("planner", {}).pop("keep_futures", None)  # videos only
    files = [recipe.policy, recipe.world_model, recipe.reward.checkpoint]
    checkpoints = {f: digest_file(Path(f)) for f in files if f and f != GT_SIM and Path(f).is_file()}
    return _plain({"controller": controller, "checkpoints": checkpoints})


def run_identity(recipe: PlannerRecipe, config: EvalConfig) -> dict[str, Any]:
    """What a closed-loop run's numbers depend on (see the module docstring)."""
    settings = {k: v for k, v in asdict(config).items() if k not in NOT_IDENTITY}
    return _plain({"config": settings, **controller_identity(recipe)})


def controller_of(summary: dict[str, Any]) -> Any:
    """The controller's part of the identity a results summary records (its ``controller`` alone where it predates it)."""
    run = summary.get("run")
    if isinstance(run, dict) and "controller" in run:
        return {"controller": run["controller"], "checkpoints": run.get("checkpoints")}
    return {"controller": summary.get("controller")}


def episode_settings(summary: dict[str, Any]) -> dict[str, Any]:
    """The settings a run's per-seed scores depend on besides its controller (``EPISODE_SETTINGS``)."""
    merged = {**summary.get("config", {}), **({"n_action_steps": summary["n_action_steps"]} if "n_action_steps" in summary else {})}
    return {key: merged.get(key) for key, _ in EPISODE_SETTINGS}


def first_difference(held: Any, given: Any, path: str = "") -> str:
    """Where two identities first differ, e.g. ``controller.rollouts: float32 there, bfloat16 here``: a setting is
    named before the checkpoints' contents, and those before the controller's label, which follows from the rest."""
    return plain_difference(held, given, path, _rank)


def _rank(key: str, value: Any) -> int:
    return 2 if key == "controller" and isinstance(value, str) else 1 if key == "checkpoints" else 0


def _plain(value: dict[str, Any]) -> dict[str, Any]:
    """Round-trip through JSON types, as a results file or a store's attributes hold it."""
    return json.loads(json.dumps(value))
