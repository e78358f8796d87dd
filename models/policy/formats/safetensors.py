"""Reading and encoding ``.safetensors`` files (Hugging Face's tensor format) without the package.

The format is small: an 8-byte little-endian header length, a JSON header naming each tensor's
dtype, shape and byte range, then the raw little-endian bytes. Reading it ourselves keeps
LeRobot checkpoints loadable with torch alone, and every check below names the file.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Mapping
from pathlib import Path

import torch

from gpc.datasets.errors import DataError

DTYPES: dict[str, torch.dtype] = {
    "F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
    "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8, "BOOL": torch.bool,
}
NAMES = {v: k for k, v in DTYPES.items()}
MAX_HEADER = 100 * 2**20  # a header larger than this is not a tensor file


def read_safetensors(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """All tensors of ``path`` (CPU, their stored dtypes); a damaged or foreign file is one ``DataError``."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) < 8:
        raise DataError(f"{path}: not a safetensors file (shorter than its 8-byte header length)")
    (size,) = struct.unpack("<Q", data[:8])
    if size > min(MAX_HEADER, len(data) - 8):
        raise DataError(f"{path}: not a safetensors file (header length {size} exceeds the file)")
    try:
        header = json.loads(data[8 : 8 + size])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: damaged safetensors header ({exc})") from None
    if not isinstance(header, dict):
        raise DataError(f"{path}: damaged safetensors header (not a JSON object)")
    body = memoryview(data)[8 + size :]
    out: dict[str, torch.Tensor] = {}
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        out[name] = _tensor(path, name, entry, body)
    return out


def _tensor(path: Path, name: str, entry: object, body: memoryview) -> torch.Tensor:
    if not isinstance(entry, dict) or not {"dtype", "shape", "data_offsets"} <= set(entry):
        raise DataError(f"{path}: tensor {name!r} has no dtype, shape and data_offsets")
    dtype = DTYPES.get(str(entry["dtype"]))
    if dtype is None:
        raise DataError(f"{path}: tensor {name!r} has dtype {entry['dtype']!r}, which gpc does not read ({', '.join(DTYPES)})")
    shape, offsets = entry["shape"], entry["data_offsets"]
    if not (isinstance(shape, list) and all(isinstance(s, int) and s >= 0 for s in shape)
            and isinstance(offsets, list) and len(offsets) == 2 and all(isinstance(o, int) for o in offsets)):
        raise DataError(f"{path}: tensor {name!r} has a malformed shape or data_offsets")
    begin, end = offsets
    numel = 1
    for s in shape:
        numel *= s
    itemsize = torch.empty((), dtype=dtype).element_size()
    if not 0 <= begin <= end <= len(body) or end - begin != numel * itemsize:
        raise DataError(f"{path}: tensor {name!r} ({entry['dtype']} {shape}) does not fit bytes {begin}..{end} "
                        f"of a {len(body)}-byte body (truncated or damaged file)")
    if numel == 0:
        return torch.empty(shape, dtype=dtype)
    raw = bytearray(body[begin:end])  # a private, writable copy
    return torch.frombuffer(raw, dtype=dtype).reshape(shape).clone()


def encode_safetensors(tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str] | None = None) -> bytes:
    """``tensors`` (any device) as the bytes of one safetensors file (write them with ``write_bytes_atomic``)."""
    header: dict[str, object] = {}
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    chunks, offset = [], 0
    for name in sorted(tensors):
        tensor = tensors[name].detach().to("cpu").contiguous()
        if tensor.dtype not in NAMES:
            raise ValueError(f"tensor {name!r}: dtype {tensor.dtype} has no safetensors name")
        raw = tensor.reshape(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b""
        header[name] = {"dtype": NAMES[tensor.dtype], "shape": list(tensor.shape), "data_offsets": [offset, offset + len(raw)]}
        chunks.append(raw)
        offset += len(raw)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the body starts 8-byte aligned
    return struct.pack("<Q", len(text)) + text + b"".join(chunks)
