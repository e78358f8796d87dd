"""Whether bfloat16 pays on this hardware.

bfloat16 autocast is fast only where the hardware computes it: a GPU that has it, or a CPU whose oneDNN has
bf16 kernels (AVX-512 or AMX). On an AVX2-only CPU it is emulated: a one-step visual world model's GPC-RANK
K=100 decision took 4.4x, a GPC-OPT M=25 one 6x, the float32 time (docs/benchmarks.md). Models ask for bf16
"where native", so one config runs at its best on either machine. That also makes a rollout's numbers depend on the
machine, so planning can pin the precision (``ROLLOUT_PRECISIONS``) and results record the dtype rollouts ran in.
"""

from __future__ import annotations

import torch

# bf16-auto: bf16 where the model asks for it and the hardware computes it; 32-true: never (a table measured on one
# machine resumes and matches on another); bf16-mixed: always, emulated if need be.
ROLLOUT_PRECISIONS = ("bf16-auto", "32-true", "bf16-mixed")


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


def check_rollout_precision(precision: str) -> str:
    if precision not in ROLLOUT_PRECISIONS:
        raise ValueError(f"--precision {precision!r}: use one of {', '.join(ROLLOUT_PRECISIONS)}")
    return precision


def rollout_bf16(asks: bool, precision: str, device_type: str) -> bool:
    """Whether a rollout of a model that ``asks`` for bf16 runs under bf16 autocast at ``precision`` on ``device_type``."""
    check_rollout_precision(precision)
    return precision == "bf16-mixed" or (precision == "bf16-auto" and asks and native_bf16(device_type))
