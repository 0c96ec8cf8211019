"""
Process-wide allocator settings for nodes that allocate the same large arrays every frame.

glibc returns the memory of a freed large array to the kernel (``munmap`` above the mmap
threshold, heap trimming above the trim threshold; the worker and numba threads allocate from
their own arenas, trimmed as soon as their top chunk exceeds the threshold). The next frame's
arrays are then fresh pages: ~2100 minor page faults per 640x480 stereo frame, each one a
kernel entry that zeroes a page, ~12 ms of process CPU per frame in ``stereo_depth_node``
(``bench/stereo_node_cpu.py``, the node alternated with and without). :func:`retain_freed_memory`
keeps freed memory in the process instead, so a frame reuses the pages of the previous one; the
price is a resident set that stays at its peak (the stereo node's peak was its resident set
already: 287 MB with and without).
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Optional

__all__ = ['retain_freed_memory', 'M_TRIM_THRESHOLD', 'M_MMAP_THRESHOLD',
           'MMAP_THRESHOLD_MAX']

#: ``mallopt`` parameter numbers (glibc ``malloc.h``).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

#: glibc's largest mmap threshold on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``) [bytes].
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


def _glibc() -> Optional[ctypes.CDLL]:
    """Return the C library when it is glibc (it has ``mallopt``), else None (musl, macOS)."""
    name = ctypes.util.find_library('c')
    try:
        libc = ctypes.CDLL(name)
    except OSError:
        return None
    return libc if hasattr(libc, 'mallopt') and hasattr(libc, 'gnu_get_libc_version') else None


def retain_freed_memory(mmap_threshold: int = MMAP_THRESHOLD_MAX,
                        trim_threshold: int = 1 << 30) -> bool:
    """
    Keep freed memory in the process: large arrays from the heap, heaps not trimmed.

    Call once at the start of a node process, before its per-frame work (the settings are
    process-wide and apply to every thread's arena).

    :param mmap_threshold: allocations of at least this many bytes are mapped (and unmapped
        when freed) one by one; below it they come from the reused heap. At most
        :data:`MMAP_THRESHOLD_MAX`.
    :param trim_threshold: free memory [bytes] at the top of a heap beyond which the heap is
        given back to the kernel.
    :return: True when both settings were applied; False on a C library without ``mallopt``
        (nothing changed) or when glibc refused a value.
    :raises ValueError: a threshold out of range.
    """
    if not 0 < mmap_threshold <= MMAP_THRESHOLD_MAX:
        raise ValueError(f'mmap_threshold must be in (0, {MMAP_THRESHOLD_MAX}] bytes, got '
                         f'{mmap_threshold}')
    if not 0 < trim_threshold < 1 << 31:
        raise ValueError(f'trim_threshold must be in (0, 2^31) bytes, got {trim_threshold}')
    libc = _glibc()
    if libc is None:
        return False
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success, 0 on error
    ok_trim = libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold)) == 1
    ok_mmap = libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
    return ok_trim and ok_mmap
