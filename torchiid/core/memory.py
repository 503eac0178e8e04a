"""Memory: how much this process may still take, and allocator settings for worker processes."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["available_memory", "undo_malloc_trim_threshold"]

#: a cgroup memory limit at or above this means "no limit" (cgroup v1 reports 2^63 - 4096)
_NO_LIMIT = 1 << 60

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


def available_memory(
    meminfo: str | os.PathLike = "/proc/meminfo",
    cgroup: str | os.PathLike = "/proc/self/cgroup",
    cgroup_root: str | os.PathLike = "/sys/fs/cgroup",
) -> int | None:
    """Bytes of memory this process can still take before the system or its container runs out.

    The smaller of the kernel's ``MemAvailable`` (free memory plus the page cache it can
    reclaim) and, where the process's memory cgroup (v2 or v1: a container's limit) has a
    limit, that limit less the cgroup's usage without its reclaimable file cache (the
    ``inactive_file`` of its ``memory.stat``). ``None`` where neither can be read (not
    Linux); the arguments are for tests.
    """
    known = []
    try:
        with open(meminfo, encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    known.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    left = _cgroup_left(cgroup, cgroup_root)
    if left is not None:
        known.append(left)
    return min(known) if known else None


def _read_int(path: str | os.PathLike) -> int | None:
    try:
        with open(path, encoding="ascii") as fh:
            text = fh.read().strip()
    except OSError:
        return None
    if text == "max":
        return _NO_LIMIT
    try:
        return int(text)
    except ValueError:
        return None


def _stat_value(path: str | os.PathLike, keys: tuple[str, ...]) -> int:
    try:
        with open(path, encoding="ascii") as fh:
            for line in fh:
                name, _, value = line.partition(" ")
                if name in keys:
                    return int(value)
    except (OSError, ValueError):
        pass
    return 0


def _cgroup_left(cgroup: str | os.PathLike, root: str | os.PathLike) -> int | None:
    """The least memory left under the limits of the process's memory cgroup and its ancestors.

    Per limited group: its limit less its usage without the file cache it can reclaim.
    ``None`` where no group on the way up has a limit (or none can be read).
    """
    try:
        with open(cgroup, encoding="ascii") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return None
    lefts = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        if controllers == "":  # cgroup v2 (unified)
            base, names = str(root), ("memory.max", "memory.current", "memory.stat")
            keys: tuple[str, ...] = ("inactive_file",)
        elif "memory" in controllers.split(","):  # cgroup v1
            base = os.path.join(root, "memory")
            names = ("memory.limit_in_bytes", "memory.usage_in_bytes", "memory.stat")
            keys = ("total_inactive_file", "inactive_file")
        else:
            continue
        parts_rel = [p for p in rel.split("/") if p]
        # the group itself, then each ancestor up to the root of the hierarchy (a container
        # may see only part of the path: the files that cannot be read are skipped)
        for depth in range(len(parts_rel), -1, -1):
            where = os.path.join(base, *parts_rel[:depth])
            limit = _read_int(os.path.join(where, names[0]))
            if limit is None or limit >= _NO_LIMIT:
                continue
            usage = _read_int(os.path.join(where, names[1])) or 0
            cache = _stat_value(os.path.join(where, names[2]), keys)
            lefts.append(max(limit - max(usage - cache, 0), 0))
    return min(lefts) if lefts else None
