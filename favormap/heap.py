"""The process heap's policy for large arrays (glibc; no-ops elsewhere).

glibc serves every block above its mmap threshold (dynamic, at most 32 MiB) with a fresh ``mmap``
and unmaps it on ``free``: each new tensor of that size is faulted in page by page on first touch.
Voxel training allocates and frees tensors of 40-190 MB at every iteration (the ray stencils of
3,000 landmarks, the optimiser's temporaries), so on two CPU cores a third of its time went to page
faults. :func:`reuse_freed_blocks` serves such blocks from the heap and keeps freed ones for reuse
(docs/measurements.md); :func:`release_free_memory` hands the heap's free pages back at the end of a
stage, so the resident memory between stages stays what the live arrays need.

The policy is process-wide, so favormap sets it only when asked: the CLI's heavy commands, ``build_map``
when its ``BuildConfig.threads`` is given and a ``Localizer`` when its ``LocalizeConfig.threads`` is (a warm
query's temporaries, a few MB each, had cost ~8,000 page faults a query on a real map).
"""

from __future__ import annotations

_libc = None  # ctypes handle of glibc, False where there is none


def _glibc():
    global _libc
    if _libc is None:
        try:
            import ctypes

            _libc = ctypes.CDLL("libc.so.6")
            _libc.mallopt, _libc.malloc_trim  # noqa: B018 - both must exist (glibc)
        except (OSError, AttributeError):
            _libc = False
    return _libc


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
_MMAP_THRESHOLD = 1 << 30  # blocks up to 1 GiB come from the heap
_TRIM_THRESHOLD = (1 << 31) - 1  # free memory at the heap's top is kept up to 2 GiB (then trimmed)
_reusing = False


def reuse_freed_blocks() -> bool:
    """Serve blocks up to 1 GiB from the heap and keep freed memory for reuse (process-wide, once).
    Returns whether the policy is in place (False without glibc)."""
    global _reusing
    libc = _glibc()
    if not libc:
        return False
    if not _reusing:
        _reusing = bool(libc.mallopt(M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(
            libc.mallopt(M_TRIM_THRESHOLD, _TRIM_THRESHOLD)
        )
    return _reusing


def release_free_memory() -> None:
    """Hand the heap's free pages back to the system (glibc ``malloc_trim``).

    Stages such as tracking free many mid-sized arrays that glibc keeps in its heap, so the process
    would otherwise enter the next stage with ~1 GB of free but resident memory on a 5,000-frame
    build (tools/bench_build_memory.py); after voxel training, the blocks kept by
    :func:`reuse_freed_blocks`."""
    libc = _glibc()
    if libc:
        libc.malloc_trim(0)
