"""Process settings: with keep_freed_memory(), large blocks come from glibc's heap, not mmap."""

from __future__ import annotations

import platform
import subprocess
import sys

# Holds an 80 MB tensor and prints the bytes glibc serves by mmap (mallinfo2().hblkhd).
PROBE = """
import ctypes, sys
if sys.argv[1] == "keep":
    from nerfbot.ops.runtime import keep_freed_memory
    assert keep_freed_memory()
import torch

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks",
                "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
a = torch.ones(80 * 2**20 // 4)
print(libc.mallinfo2().hblkhd)
"""
BLOCK = 80 * 2**20


def _mmapped_bytes(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True,
                          check=True)
    return int(done.stdout.strip())


def test_keep_freed_memory_serves_large_blocks_from_the_heap():
    from nerfbot.ops.runtime import keep_freed_memory

    if platform.libc_ver()[0] != "glibc":  # no mallopt: the call must change nothing, say so
        assert keep_freed_memory() is False
        return
    assert _mmapped_bytes("default") >= BLOCK  # glibc's default: one fresh mapping per block
    assert _mmapped_bytes("keep") < BLOCK // 8


def test_keep_freed_memory_reports_whether_it_applied():
    # Run in a child: the setting is process-wide and cannot be undone here.
    code = "from nerfbot.ops.runtime import keep_freed_memory as k; print(k(), k())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    expected = platform.libc_ver()[0] == "glibc"
    assert done.stdout.split() == [str(expected)] * 2  # idempotent
