"""Keep freed memory in the process for the evaluation stages (glibc ``mallopt``).

The evaluation stages allocate and free full-frame temporaries (600 x 600 float
arrays of 1.4-8.6 MB) thousands of times per sequence.  glibc returns each of
them to the kernel (``mmap``/``munmap`` above its mmap threshold, heap trimming
below it), so every new array page-faults again: on a 30-frame
``evaluate_depth`` run that was 2.1 million minor page faults and 5.5 s of
system time next to 8.9 s of user time.  Raising the mmap threshold to glibc's
maximum and keeping up to ``trim_mb`` of freed heap cut it to 86 thousand
faults and 0.5 s (``benchmarks/evaluation_budget.py`` measures the stages).
Results are unchanged: only where the allocator takes memory from.

Nothing happens on a C library without ``mallopt`` (macOS, musl): the stages
are then only slower.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
#: glibc's largest mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX); larger values are refused
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


def keep_freed_memory(trim_mb: int = 512, top_pad_mb: int = 64) -> bool:
    """Ask glibc to serve allocations up to 32 MB from the heap and keep up to ``trim_mb`` of freed heap.

    Returns whether the C library accepted all three settings (False where there is no ``mallopt``)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX) == 1
    ok &= mallopt(M_TRIM_THRESHOLD, int(trim_mb) * 1024 * 1024) == 1
    ok &= mallopt(M_TOP_PAD, int(top_pad_mb) * 1024 * 1024) == 1
    return bool(ok)
