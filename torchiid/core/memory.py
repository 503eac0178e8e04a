"""Process-wide memory-allocator settings for worker processes."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["undo_malloc_trim_threshold"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def undo_malloc_trim_threshold() -> bool:
    """Give glibc's allocator back the behaviour torch's tensors need, if it was taken away.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Setting that variable
    also switches off glibc's dynamic mmap threshold, so every buffer above 128 KiB is mapped
    and unmapped on each allocation and its pages faulted in again: measured, a decomposition
    at 512×384 ran 2–4× slower in such a process. This sets the thresholds explicitly to what
    the dynamic rule converges to for large tensors (mmap above 32 MiB, trim above 128 MiB).
    Linux with glibc only; elsewhere, or without the variable, it does nothing.

    Returns:
        whether the thresholds were set.
    """
    if not sys.platform.startswith("linux") or "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024) == 1
    return ok and mallopt(_M_TRIM_THRESHOLD, 128 * 1024 * 1024) == 1
