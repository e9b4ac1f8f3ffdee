"""Process-wide settings for long training and rendering jobs."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: Free memory at the top of the heap goes back to the OS only above this (bytes; the largest
#: value mallopt takes).
_TRIM_ABOVE = 2**31 - 1


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep and reuse freed memory instead of returning it to the OS.

    By default glibc serves every block above 32 MB with a fresh ``mmap`` and unmaps it when it
    is freed, so the kernel zero-fills every page again the next time. A training step allocates
    many such blocks (131k samples x 150 features is 80 MB). With mmap off and trimming only above
    2 GB, they come from the heap and are reused. Measured on the tabletop at 128x128, 60 steps,
    one process each: ``ngp`` 0.30 against 0.33 s per step (the 180 s
    runs got as many steps as before), ``tensorf`` 0.55 against 0.88 s, peak memory within 5 %.
    The process keeps its peak memory reserved until it exits, as it would with jemalloc or
    tcmalloc.

    It acts on the whole process and works best before large allocations are made: the
    ``nerfbot`` command and benchmark points call it first thing; library users can call it at
    start-up. Returns False, changing nothing, where the C library has no ``mallopt``.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others have no mallopt
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_ABOVE))
