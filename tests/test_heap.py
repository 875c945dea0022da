"""favormap.heap: glibc's policy for large blocks during voxel training."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_large_blocks_come_from_the_heap_once_reuse_is_on():
    """glibc serves a 64 MB block with its own mapping (mallinfo2's hblks), which is unmapped on free
    and mapped (and zeroed) afresh for the next tensor of that size; with the policy on, the block
    comes from the heap and is reused, and release_free_memory hands it back afterwards."""
    code = r"""
import ctypes, sys
import numpy as np
from favormap.heap import release_free_memory, reuse_freed_blocks

class Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Mallinfo2
if sys.argv[1] == "on":
    assert reuse_freed_blocks() and reuse_freed_blocks()
h0 = libc.mallinfo2().hblks
a = np.ones(8 << 20)  # 64 MB
mapped = libc.mallinfo2().hblks - h0
del a
kept = libc.mallinfo2().fordblks  # free bytes kept in the heap
release_free_memory()
print(mapped, kept >= 64 << 20, libc.mallinfo2().fordblks < 64 << 20)
"""
    out = {}
    for mode in ("on", "off"):
        r = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True)
        if r.returncode and "mallinfo2" in r.stderr:
            pytest.skip("glibc without mallinfo2 (< 2.33)")
        assert r.returncode == 0, r.stderr
        out[mode] = r.stdout.split()
    assert out["off"][:2] == ["1", "False"]  # its own mapping, unmapped on free
    assert out["on"] == ["0", "True", "True"]  # from the heap, kept for reuse, then handed back
