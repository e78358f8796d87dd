"""Frozen dataclass configs <-> plain dicts (the form checkpoints store as hyper-parameters).

Plain means dicts, tuples, strings and numbers only, so a checkpoint loads with
``torch.load(weights_only=True)`` and reads back without this library's classes pickled in.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Callable
from typing import Any, TypeVar, cast

T = TypeVar("T")


def to_plain(config: Any) -> dict[str, Any]:
    """Nested dataclasses become nested dicts; tuples stay tuples."""
    return dataclasses.asdict(config)


def _tuples(value: Any) -> Any:
    """Lists (as YAML or JSON round trips write tuples) become tuples, recursively."""
    if isinstance(value, (list, tuple)):
        return tuple(_tuples(v) for v in value)
    return value


def from_plain(cls: type[T], data: dict[str, Any] | T) -> T:
    """Rebuild ``cls`` from ``to_plain``'s output; unknown keys raise a ValueError naming them."""
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ValueError(f"{cls.__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    # T is unbounded (PlainConfig's mixin binds it too), so mypy cannot see cls is a dataclass.
    names = {f.name for f in dataclasses.fields(cast(Any, cls)) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field(s) {', '.join(unknown)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            kwargs[name] = from_plain(cast(type, hint), value)
        else:
            kwargs[name] = _tuples(value)
    return cls(**kwargs)


class PlainConfig:
    """Mixin for top-level configs: ``to_dict`` for checkpoints, ``from_dict`` to rebuild (also accepts an instance)."""

    def to_dict(self) -> dict[str, Any]:
        return to_plain(self)

    @classmethod
    def from_dict(cls: type[T], data: Any) -> T:
        return from_plain(cls, dict(data) if isinstance(data, typing.Mapping) else data)


class _Absent:
    def __repr__(self) -> str:
        return "absent"


ABSENT = _Absent()  # a key one record has and the other lacks


def first_difference(held: Any, given: Any, path: str = "", rank: Callable[[str, Any], int] = lambda key, value: 0) -> str:
    """Where two plain records (a stored one, "there", and a wanted one, "here") first differ, by key path, e.g.
    ``config.optim.lr: 0.001 there, 0.002 here``; ``rank(key, held value)``: keys of a higher rank are compared later."""
    if isinstance(held, dict) and isinstance(given, dict):
        for key in sorted(set(held) | set(given), key=lambda k: (rank(k, held.get(k)), k)):
            if held.get(key, ABSENT) != given.get(key, ABSENT):
                return first_difference(held.get(key, ABSENT), given.get(key, ABSENT), f"{path}.{key}" if path else key, rank)
    shown = [value if value is ABSENT or len(repr(value)) <= 60 else "differs" for value in (held, given)]
    return f"{path or 'run'}: {shown[0]} there, {shown[1]} here"
