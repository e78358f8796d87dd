"""The wire format of `gpc serve`: msgpack maps whose numpy arrays are spelled out (dtype, shape, bytes).

Both ends import this module: it needs numpy and msgpack only (the robot-side client runs without torch).
Nothing is ever unpickled: an array travels as ``{"__nd__": 1, "dtype": "<f4", "shape": [..], "data": bytes}``
with its dtype from a fixed allow-list (no object arrays), msgpack extension types are refused, and a
decoded array is checked to hold exactly ``prod(shape) * itemsize`` bytes before numpy sees it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import msgpack
import numpy as np

WIRE_VERSION = 1  # bumped when a message changes meaning; the handshake carries it
ARRAY_TAG = "__nd__"
# Plain numeric dtypes only, little-endian: what observations and actions are made of.
DTYPES = frozenset(np.dtype(name).str for name in (
    "bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float16", "float32", "float64"))
MAX_DIMS = 8


class WireError(ValueError):
    """A message that is not well-formed gpc wire format (the answer names what is wrong)."""


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        array = np.ascontiguousarray(obj)
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        if dtype.str not in DTYPES:
            raise WireError(f"array of dtype {obj.dtype}: the wire carries {', '.join(sorted(DTYPES))} only")
        return {ARRAY_TAG: 1, "dtype": dtype.str, "shape": list(array.shape), "data": array.astype(dtype, copy=False).tobytes()}
    if isinstance(obj, np.generic):
        return obj.item()
    raise WireError(f"{type(obj).__name__}: not sendable (numbers, strings, bytes, lists, maps and numeric arrays are)")


def pack(message: Mapping[str, Any]) -> bytes:
    """One message as bytes; numpy arrays and scalars are encoded, anything else msgpack does not know is refused."""
    return msgpack.packb(message, default=_encode, use_bin_type=True)


def _refuse_ext(code: int, data: bytes) -> Any:
    raise WireError(f"msgpack extension type {code}: refused (the wire carries no extension types, so nothing is unpickled)")


def _decode_array(obj: dict[str, Any]) -> Any:
    if obj.get(ARRAY_TAG) != 1:
        return obj
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise WireError(f"array dtype {dtype!r}: the wire carries {', '.join(sorted(DTYPES))} only")
    if (not isinstance(shape, list) or len(shape) > MAX_DIMS
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise WireError(f"array shape {shape!r}: a list of at most {MAX_DIMS} non-negative integers")
    if not isinstance(data, bytes) or len(data) != math.prod(shape) * np.dtype(dtype).itemsize:
        raise WireError(f"array of dtype {dtype} and shape {tuple(shape)}: its data is not {math.prod(shape)} items")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def unpack(raw: bytes | str) -> dict[str, Any]:
    """A received message: a map with string keys, arrays decoded (read-only views of the frame's bytes)."""
    if not isinstance(raw, bytes):
        raise WireError("text frame: messages are binary msgpack")
    try:
        message = msgpack.unpackb(raw, raw=False, strict_map_key=True, ext_hook=_refuse_ext, object_hook=_decode_array)
    except WireError:
        raise
    except Exception as exc:  # msgpack's own errors: truncated, extra data, invalid UTF-8, ...
        raise WireError(f"malformed msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(message, dict):
        raise WireError(f"message is a msgpack {type(message).__name__}; a map is expected")
    return message


def error(text: str, **extra: Any) -> bytes:
    """The one answer to a bad request: what was wrong, in one line."""
    return pack({"type": "error", "error": text, **extra})
