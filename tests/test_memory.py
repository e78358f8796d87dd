"""Freed memory stays in the process (``gpc.harness.memory``): a large block made again costs no new page faults."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

MAKE_AND_FREE = """
import ctypes, resource, sys
from gpc.harness.memory import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
size = 64 << 20  # above glibc's largest mmap threshold, as a torch activation of a K=100 rollout is
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    block = libc.malloc(size)
    ctypes.memset(block, 1, size)  # what filling a tensor does: touches every page
    libc.free(block)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def page_faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", MAKE_AND_FREE, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="keeping freed memory is glibc's mallopt (Linux)")
def test_a_block_made_again_reuses_its_pages():
    """By default each 64 MiB block faults its 16,384 pages in anew; kept, the pages of the first are reused."""
    default, kept = page_faults("default"), page_faults("keep")
    assert default > 20 * 16_000 * 0.9
    assert kept < default / 5
