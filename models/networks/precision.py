"""Whether bfloat16 pays on this hardware.

bfloat16 autocast is fast only where the hardware computes it: a GPU that has it, or a CPU whose oneDNN has
bf16 kernels (AVX-512 or AMX). On an AVX2-only CPU it is emulated: a one-step visual world model's GPC-RANK
K=100 decision took 4.4x, a GPC-OPT M=25 one 6x, the float32 time (docs/benchmarks.md). Models ask for bf16
"where native", so one config runs at its best on either machine.
"""

from __future__ import annotations

import torch


def native_bf16(device_type: str) -> bool:
    """Whether ``device_type`` (``cpu``, ``cuda``, ...) computes bfloat16 natively."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device_type == "cpu":
        try:
            return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
        except (AttributeError, RuntimeError):  # a torch build without oneDNN's query
            return False
    return False
