"""Several world models of one task planning as one: a score that counts what they agree on.

One model's error decides which proposal wins when the proposals differ by less than that error
(Block Stacking's grasps). An ensemble (PETS' remedy, Chua et al. 2018) scores each candidate by
every member's prediction: the mean of the members' rewards, less ``pessimism`` times their
spread, so a candidate that only one member likes, or that the ascent found by exploiting one
member, is doubted. ``gpc ensemble A.ckpt B.ckpt ... --out E.ckpt`` writes it as one checkpoint
(the members' planning weights and the rule), so every command that takes ``--world-model``
takes it, and a results identity hashes it like any checkpoint.

The members must predict the same thing from the same inputs: task, observation, history length,
action and state (or frame) shape. They may differ in anything else (seed, data, steps, size).
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Sequence
from typing import Any, cast

import torch
from torch import nn

from gpc.datasets.errors import DataError
from gpc.datasets.sequence import recorded_split
from gpc.models.training.checkpoint import META_KEY, checkpoint_meta, for_planning, read_checkpoint, rebuild
from gpc.models.world_models.config import KIND as MEMBER_KIND
from gpc.models.world_models.config import VisualWorldModelConfig
from gpc.models.world_models.module import WorldModelModule

KIND = "world_model_ensemble"
MEMBERS = "members"
MAX_MEMBERS = 64


class WorldModelEnsemble(nn.Module):
    """Members' futures averaged (``rollout``), and their rewards combined as mean - pessimism x std (``combine``)."""

    def __init__(self, members: Sequence[WorldModelModule], pessimism: float = 0.0) -> None:
        super().__init__()
        check_rule(len(members), pessimism)
        check_members(members, [f"member {i}" for i in range(len(members))])
        self.nets = nn.ModuleList(members)  # registered: moved, frozen and put in eval mode with the ensemble
        self.pessimism = float(pessimism)

    @property
    def members(self) -> list[WorldModelModule]:
        return cast(list[WorldModelModule], list(self.nets))

    @property
    def config(self) -> Any:
        """The first member's config: task and observation, which every member shares (the pairing check reads it)."""
        return self.members[0].config

    @property
    def obs_key(self) -> str:
        return self.members[0].obs_key

    @property
    def n_obs_steps(self) -> int:
        return self.members[0].n_obs_steps

    @property
    def data_record(self) -> dict[str, Any]:
        """The members' training record where they held out the same episodes (``gpc eval world-model`` judges on those)."""
        first = self.members[0].data_record
        key = (first.get("held_out"), recorded_split(first), first.get("datasets"))
        if any((r.get("held_out"), recorded_split(r), r.get("datasets")) != key for r in (m.data_record for m in self.members)):
            raise DataError("the ensemble's members held out different episodes; judge it on stores none of them "
                            "trained on (--split all)")
        return first

    def rollout_members(self, history: torch.Tensor, actions: torch.Tensor, **options: Any) -> torch.Tensor:
        """Each member's ``rollout``, stacked: ``(E, K, T, ...)``."""
        return torch.stack([member.rollout(history, actions, **options) for member in self.members])

    def rollout(self, history: torch.Tensor, actions: torch.Tensor, **options: Any) -> torch.Tensor:
        """The members' mean prediction (``WorldModel.rollout``; what videos show and ``gpc eval world-model`` judges)."""
        return self.rollout_members(history, actions, **options).mean(0)

    def combine(self, scores: torch.Tensor) -> torch.Tensor:
        """``(E, ...)`` one score per member -> ``(...)``: their mean less ``pessimism`` times their spread (std over members)."""
        mean = scores.mean(0)
        if not self.pessimism:
            return mean
        return mean - self.pessimism * scores.std(0, unbiased=False)  # (torch's gradient of a zero spread is 0)

    def to(self, *args: Any, **kwargs: Any) -> WorldModelEnsemble:
        """Each member moved by its own ``to`` (a Lightning module tracks its device there)."""
        for member in self.members:
            member.to(*args, **kwargs)
        return self

    def set_rollout_precision(self, precision: str) -> str:
        """Every member's (``WorldModelModule.set_rollout_precision``); the dtypes they run in (``bfloat16+float32`` where
        members differ: results record it)."""
        return "+".join(sorted({member.set_rollout_precision(precision) for member in self.members}))

    def summary(self) -> dict[str, Any]:
        return {"members": len(self.members), "pessimism": self.pessimism}


def check_rule(members: int, pessimism: float) -> None:
    if not 2 <= members <= MAX_MEMBERS:
        raise ValueError(f"an ensemble needs 2..{MAX_MEMBERS} members, got {members}")
    if not 0 <= pessimism < math.inf:  # NaN fails too
        raise ValueError(f"--pessimism {pessimism}: must be a finite number >= 0 (0: the members' mean reward)")


def check_members(members: Sequence[WorldModelModule], names: Sequence[Any]) -> None:
    """Refuse a member that predicts other observations, or from other inputs, than the first (``ValueError``)."""
    for member, name in zip(members[1:], names[1:], strict=True):
        difference = _mismatch(members[0], member)
        if difference:
            raise ValueError(f"{name}: {difference} ({names[0]}'s); an ensemble's members predict the same "
                             "observations from the same inputs")


def _mismatch(a: WorldModelModule, b: WorldModelModule) -> str:
    """What a second member predicts differently from the first ("" when nothing)."""
    ca, cb = a.config, b.config
    checks = [("task", ca.task, cb.task), ("observation", a.obs_key, b.obs_key), ("history", a.n_obs_steps, b.n_obs_steps),
              ("action size", ca.dynamics.action_dim, cb.dynamics.action_dim)]
    if isinstance(ca, VisualWorldModelConfig) and isinstance(cb, VisualWorldModelConfig):
        checks.append(("frame size", ca.dynamics.resolution, cb.dynamics.resolution))
    elif not isinstance(ca, VisualWorldModelConfig) and not isinstance(cb, VisualWorldModelConfig):
        checks.append(("state size", ca.dynamics.state_dim, cb.dynamics.state_dim))
    for name, x, y in checks:
        if x != y:
            return f"{name} {y!r}, not {x!r}"
    return ""


def ensemble_checkpoint(paths: Sequence[str | os.PathLike], pessimism: float = 0.0, half: bool = False) -> dict[str, Any]:
    """The checkpoint ``gpc ensemble`` writes: each member's planning checkpoint (``gpc export``'s) and the rule.

    Checked as it is built: every file a world model of one task, and the members buildable as an ensemble.
    """
    check_rule(len(paths), pessimism)
    members = [for_planning(read_checkpoint(path, MEMBER_KIND), half) for path in paths]
    modules = [rebuild(WorldModelModule, ckpt, path, "world model") for ckpt, path in zip(members, paths, strict=True)]
    try:
        check_members(modules, [str(p) for p in paths])
    except ValueError as exc:
        raise DataError(str(exc)) from None
    config = modules[0].config
    meta = checkpoint_meta(KIND, config.task, obs=config.obs_type, members=len(members), pessimism=float(pessimism),
                           sources=[str(p) for p in paths])
    return {META_KEY: meta, MEMBERS: members}


def save_ensemble(checkpoint: dict[str, Any]) -> bytes:
    buffer = io.BytesIO()
    torch.save(checkpoint, buffer)
    return buffer.getvalue()


def load_any(path: str | os.PathLike, task: str | None = None, map_location: Any = "cpu") -> WorldModelModule | WorldModelEnsemble:
    """A world model to plan with: one model's checkpoint or an ensemble's (``gpc ensemble``), told apart by its record."""
    ckpt = read_checkpoint(path, None, task=task, map_location=map_location)
    kind = ckpt[META_KEY].get("kind")
    if kind == MEMBER_KIND:
        return rebuild(WorldModelModule, ckpt, path, "world model")
    if kind != KIND:
        raise DataError(f"{path}: is a {kind!r} checkpoint, expected a {MEMBER_KIND!r} checkpoint (or a {KIND!r})")
    return _ensemble(ckpt, path)


def _ensemble(ckpt: dict[str, Any], path: str | os.PathLike) -> WorldModelEnsemble:
    members = ckpt.get(MEMBERS)
    if not isinstance(members, list) or len(members) != ckpt[META_KEY].get("members"):
        raise DataError(f"{path}: ensemble checkpoint without its {ckpt[META_KEY].get('members')} members")
    modules = [rebuild(WorldModelModule, member, f"{path} (member {i})", "world model") for i, member in enumerate(members)]
    try:
        return WorldModelEnsemble(modules, ckpt[META_KEY].get("pessimism", 0.0)).eval()
    except ValueError as exc:
        raise DataError(f"{path}: {exc}") from None

