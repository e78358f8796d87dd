"""Keep freed memory in the process, so large tensors do not pay a page fault per 4 KiB each time they are made.

A planning decision makes and frees the same large activations again and again (a GPC-RANK K=100 call for 10
lockstep episodes rolls 1,000 frames through the visual model's U-Net: hundreds of MB per activation). glibc serves
each block above its mmap threshold (at most 32 MB) with an mmap of its own and unmaps it when freed, and trims the
heap's free top; either way the next block of that size faults its pages in again, zeroed, from the kernel. On two
cores that was 60% of a float32 rollout's time: 1,000 candidates took 59 s, and 15 s with every block served from a
heap that is never trimmed (docs/benchmarks.md). The price is a resident set that stays at its peak, which a planning
or training process reaches in its first step anyway. ``gpc`` turns this on in each of its processes; a program that
plans through the Python API calls ``keep_freed_memory()`` once.
"""

from __future__ import annotations

import ctypes
import sys

M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)


def keep_freed_memory() -> bool:
    """Serve every allocation from the heap (no mmap) and never trim it; False where the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl and other C libraries: no libc.so.6, or no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # -1 turns trimming off altogether (mallopt(3)); a positive threshold is an int, at most 2 GiB, which a K=100
    # decision's free top exceeds, so it would still be returned and faulted in again each decision.
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, -1))
