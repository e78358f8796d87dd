"""Loading Diffusion Policy's ``.ckpt`` files without running code that a pickle could carry.

A ``.ckpt`` is ``torch.save(payload, pickle_module=dill)``: tensors, plain Python values and
the run's OmegaConf config. Unpickling calls whatever callable the file names, so a crafted
file could run anything; ``torch.load(weights_only=True)`` refuses the OmegaConf classes these
files need. Here the unpickler rebuilds only an allow-list: tensors and their storages, builtin
containers and scalars, numpy arrays, and OmegaConf's config nodes, which become inert
stand-ins that ``plain`` turns into dicts and lists (so neither omegaconf nor dill is needed).
Any other name in the file is refused before anything is called.
"""

from __future__ import annotations

import collections
import os
import pickle
import types
import typing
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError

try:  # numpy >= 2 moved its internals; both names appear in pickles
    from numpy._core import multiarray as _multiarray
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]

# dill writes builtin types as ``dill._dill._load_type(name)``; only these names are answered.
_BUILTIN_TYPES: dict[str, type] = {
    t.__name__: t for t in (dict, list, tuple, set, frozenset, int, float, complex, str, bytes, bytearray, bool, slice)
}
_BUILTIN_TYPES["NoneType"] = type(None)


class ConfigNode:
    """Stands in for an OmegaConf node (DictConfig, ListConfig, AnyNode, ...): keeps the pickled state, runs nothing."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state


class ConfigMeta(ConfigNode):
    """Stands in for OmegaConf's node metadata (ignored by ``plain``)."""


def _load_type(name: str) -> type:
    if name not in _BUILTIN_TYPES:
        raise pickle.UnpicklingError(f"dill._dill._load_type({name!r})")
    return _BUILTIN_TYPES[name]


def _encode(text: str, encoding: str = "latin1") -> bytes:
    """Protocol 2 writes ``bytes`` as ``_codecs.encode(text, 'latin1')``; only text codecs are answered."""
    if encoding not in ("latin1", "latin-1", "utf-8", "utf8", "ascii"):
        raise pickle.UnpicklingError(f"_codecs.encode(..., {encoding!r})")
    return text.encode(encoding)


ALLOWED: dict[tuple[str, str], Any] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("torch._utils", "_rebuild_tensor_v2"): torch._utils._rebuild_tensor_v2,
    ("torch._utils", "_rebuild_parameter"): torch._utils._rebuild_parameter,
    ("torch", "Size"): torch.Size,
    ("typing", "Any"): typing.Any,
    ("dill._dill", "_load_type"): _load_type,
    ("_codecs", "encode"): _encode,
    ("omegaconf.dictconfig", "DictConfig"): ConfigNode,
    ("omegaconf.listconfig", "ListConfig"): ConfigNode,
    ("omegaconf.nodes", "AnyNode"): ConfigNode,
    ("omegaconf.nodes", "StringNode"): ConfigNode,
    ("omegaconf.nodes", "IntegerNode"): ConfigNode,
    ("omegaconf.nodes", "FloatNode"): ConfigNode,
    ("omegaconf.nodes", "BooleanNode"): ConfigNode,
    ("omegaconf.base", "ContainerMetadata"): ConfigMeta,
    ("omegaconf.base", "Metadata"): ConfigMeta,
    **{(mod, "_reconstruct"): _multiarray._reconstruct for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(mod, "scalar"): _multiarray.scalar for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    **{("builtins", name): t for name, t in _BUILTIN_TYPES.items() if name != "NoneType"},
    **{("__builtin__", name): t for name, t in _BUILTIN_TYPES.items() if name != "NoneType"},
}


class RestrictedUnpickler(pickle.Unpickler):
    """A ``pickle.Unpickler`` that resolves only ``ALLOWED`` names (torch handles storages before asking)."""

    def find_class(self, module: str, name: str) -> Any:
        found = ALLOWED.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"refused to rebuild {module}.{name}")
        return found


def _pickle_module() -> types.ModuleType:
    module = types.ModuleType("gpc_restricted_pickle")
    module.Unpickler = RestrictedUnpickler  # type: ignore[attr-defined]
    module.load = lambda f, **kw: RestrictedUnpickler(f, **kw).load()  # type: ignore[attr-defined]
    module.__dict__.update(dumps=pickle.dumps, dump=pickle.dump, HIGHEST_PROTOCOL=pickle.HIGHEST_PROTOCOL)
    return module


def load_restricted(path: str | os.PathLike) -> Any:
    """``torch.load`` of ``path`` through the restricted unpickler, on the CPU; a refusal is one ``DataError``."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False, pickle_module=_pickle_module())
    except pickle.UnpicklingError as exc:
        raise DataError(f"{path}: {exc}: not a type a Diffusion Policy checkpoint holds, so the file is refused "
                        "unread (a crafted or unsupported file)") from None
    except Exception as exc:  # truncated zip, foreign file: torch raises many types
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
        raise DataError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {first})") from None


def plain(value: Any) -> Any:
    """Stand-in config nodes -> dicts, lists and values; containers recursed; anything else as it is."""
    if isinstance(value, ConfigNode):
        state = value.state if isinstance(value.state, dict) else {}
        content = state.get("_content", state.get("_val"))
        return plain(content)
    if isinstance(value, dict):
        return {plain(k): plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    if isinstance(value, tuple):
        return tuple(plain(v) for v in value)
    return value
