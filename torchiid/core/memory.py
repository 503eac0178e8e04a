"""Memory: how much this process may still take, and allocator settings for worker processes."""

from __future__ import annotations

import ctypes
import functools
import os
import sys
from collections.abc import Callable

from torchiid.core.exceptions import ParameterError

__all__ = [
    "MEMORY_LIMIT_VARIABLE",
    "available_memory",
    "memory_limit",
    "release_free_memory",
    "share_one_malloc_arena",
    "undo_malloc_trim_threshold",
]

#: the environment variable of a user's memory cap, in GB (``TORCHIID_MEMORY_LIMIT=4``)
MEMORY_LIMIT_VARIABLE = "TORCHIID_MEMORY_LIMIT"

#: a cgroup memory limit at or above this means "no limit" (cgroup v1 reports 2^63 - 4096)
_NO_LIMIT = 1 << 60

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The process's C library where it is glibc (Linux), else ``None``; looked up once."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)  # the libraries the process has loaded: no search on disk
        libc.gnu_get_libc_version  # noqa: B018 - glibc's own symbol (musl has none)
    except (OSError, AttributeError):
        return None
    return libc


def _mallopt() -> Callable[[int, int], int] | None:
    """The C library's ``mallopt`` (glibc), or ``None`` off Linux or with another C library."""
    libc = _glibc()
    if libc is None:
        return None
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def release_free_memory() -> bool:
    """Hand the memory the allocator holds free back to the system (glibc's ``malloc_trim``).

    glibc keeps freed memory that lies below memory still in use, and a freed large buffer
    raises its threshold for mapping the next ones, so after Stage 0 (onnxruntime's
    activations, the segmentation's arrays) and after the half-size alternations a process
    holds tens of megabytes it no longer uses. :func:`~torchiid.model.decompose` calls this
    at those two points, before the solves that set a photo's peak; a call takes a few
    milliseconds at 512 px. It acts on the whole process's allocator, as any
    ``malloc_trim``: what other code of the process has freed goes back too, and its other
    threads' allocations wait for it. Linux with glibc only; elsewhere it does nothing.

    Returns:
        whether memory was handed back.
    """
    libc = _glibc()
    if libc is None:
        return False
    trim = libc.malloc_trim
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(trim(0) == 1)


def share_one_malloc_arena() -> bool:
    """Let every thread that has not yet allocated share glibc's main arena from now on.

    glibc gives each thread of a process an allocator arena of its own at its first
    allocation (up to 8 per core), and memory freed into an arena serves that arena's threads
    alone. A decomposition's threads (onnxruntime's and torch's pools, the kernels' bands,
    the segmentation) allocate little and seldom: sharing one arena costs them next to no
    waiting, while arenas of their own would mostly hold freed memory at the process's peak.
    The ``torchiid`` command and the worker processes of ``--workers N`` call this before
    their first image; a Python program that imports torchiid keeps the allocator it has.
    Linux with glibc only; a ``MALLOC_ARENA_MAX`` set in the environment is left as it is.

    Returns:
        whether the setting was made.
    """
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    mallopt = _mallopt()
    return mallopt is not None and mallopt(_M_ARENA_MAX, 1) == 1


def undo_malloc_trim_threshold() -> bool:
    """Give glibc's allocator back the behaviour torch's tensors need, if it was taken away.

    Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Setting that variable
    also switches off glibc's dynamic mmap threshold, so every buffer above 128 KiB is mapped
    and unmapped on each allocation and its pages faulted in again, which makes a
    decomposition several times slower. This sets the thresholds explicitly to what
    the dynamic rule converges to for large tensors (mmap above 32 MiB, trim above 128 MiB).
    Linux with glibc only; elsewhere, or without the variable, it does nothing.

    Returns:
        whether the thresholds were set.
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return False
    mallopt = _mallopt()
    if mallopt is None:
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024) == 1
    return ok and bool(mallopt(_M_TRIM_THRESHOLD, 128 * 1024 * 1024) == 1)


def available_memory(
    meminfo: str | os.PathLike[str] = "/proc/meminfo",
    cgroup: str | os.PathLike[str] = "/proc/self/cgroup",
    cgroup_root: str | os.PathLike[str] = "/sys/fs/cgroup",
) -> int | None:
    """Bytes of memory this process can still take before the system or its container runs out.

    The smaller of the kernel's ``MemAvailable`` (free memory plus the page cache it can
    reclaim) and, where the process's memory cgroup or one of its ancestors (v2 or v1: a
    container's limit) has a limit, that limit less the group's usage without its
    reclaimable file cache (``inactive_file`` in its ``memory.stat``; in v2 the lower of
    ``memory.high`` and ``memory.max``). ``None`` where neither can be read (not Linux).
    Never raises: files it cannot read or parse are skipped. The arguments are for tests.

    Several processes on one machine (``--workers``, a Dask worker per core) each see the
    same figure: it says what is left now, not what the others will take.
    """
    known = []
    info = _key_values(meminfo, ":")
    if "MemAvailable" in info:
        known.append(info["MemAvailable"] * 1024)  # in kB
    left = _cgroup_left(cgroup, cgroup_root)
    if left is not None:
        known.append(left)
    return min(known) if known else None


def memory_limit(gigabytes: str | float | None = None) -> int | None:
    """The memory cap a user set, in bytes: at most this much for one decomposition.

    Args:
        gigabytes: the cap in GB (10^9 bytes), a number or its text (``"2.5"``); by default
            the value of the environment variable ``TORCHIID_MEMORY_LIMIT``. Unset, empty or
            0 means no cap.

    Returns:
        bytes, or ``None`` for no cap.

    Raises:
        ParameterError: the value is not a number of GB >= 0 (the message names where it
            came from).
    """
    where = "the memory limit"
    if gigabytes is None:
        gigabytes = os.environ.get(MEMORY_LIMIT_VARIABLE, "")
        where = MEMORY_LIMIT_VARIABLE
    text = str(gigabytes).strip()
    if text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0 or value == float("inf"):
        raise ParameterError(f"{where} must be a number of GB >= 0 (e.g. 4 or 2.5), got {text!r}")
    return None if value == 0 else int(value * 1e9)


def _read_text(path: str | os.PathLike[str]) -> str | None:
    """The file's text, or ``None`` if it cannot be read (undecodable bytes are replaced)."""
    try:
        with open(path, encoding="ascii", errors="replace") as fh:
            return fh.read()
    except (OSError, ValueError):
        return None


def _read_int(path: str | os.PathLike[str]) -> int | None:
    """A cgroup limit or usage file: an integer, ``max`` (no limit), else ``None``."""
    text = _read_text(path)
    if text is None:
        return None
    text = text.strip()
    if text == "max":
        return _NO_LIMIT
    try:
        return int(text)
    except ValueError:
        return None


def _key_values(path: str | os.PathLike[str], separator: str = " ") -> dict[str, int]:
    """``name value`` lines (``memory.stat``; ``/proc/meminfo`` with ``:``) as a dict."""
    out: dict[str, int] = {}
    for line in (_read_text(path) or "").splitlines():
        name, _, rest = line.partition(separator)
        fields = rest.split()
        if fields:
            try:
                out.setdefault(name.strip(), int(fields[0]))
            except ValueError:
                continue
    return out


#: per cgroup version: the limit files (the lowest counts), the usage file, and the
#: ``memory.stat`` keys of the reclaimable file cache in order of preference (v1's
#: ``total_inactive_file`` covers the group's children, as its usage does)
_V2: tuple[tuple[str, ...], str, tuple[str, ...]] = (
    ("memory.max", "memory.high"),
    "memory.current",
    ("inactive_file",),
)
_V1: tuple[tuple[str, ...], str, tuple[str, ...]] = (
    ("memory.limit_in_bytes",),
    "memory.usage_in_bytes",
    ("total_inactive_file", "inactive_file"),
)


def _cgroup_left(cgroup: str | os.PathLike[str], root: str | os.PathLike[str]) -> int | None:
    """The least memory left under the limits of the process's memory cgroup and its ancestors.

    Per limited group: its limit less its usage without the file cache it can reclaim.
    ``None`` where no group on the way up has a limit (or none can be read).
    """
    text = _read_text(cgroup)
    if text is None:
        return None
    lefts = []
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        if controllers == "":  # cgroup v2 (unified)
            base, (limit_files, usage_file, keys) = str(root), _V2
        elif "memory" in controllers.split(","):  # cgroup v1
            base, (limit_files, usage_file, keys) = os.path.join(root, "memory"), _V1
        else:
            continue
        parts_rel = [p for p in rel.split("/") if p and p not in (".", "..")]
        # the group itself, then each ancestor up to the root of the hierarchy (a container
        # may see only part of the path: the files that cannot be read are skipped)
        for depth in range(len(parts_rel), -1, -1):
            where = os.path.join(base, *parts_rel[:depth])
            limits = [_read_int(os.path.join(where, name)) for name in limit_files]
            limit = min((v for v in limits if v is not None), default=None)
            if limit is None or limit >= _NO_LIMIT:
                continue
            usage = _read_int(os.path.join(where, usage_file)) or 0
            stat = _key_values(os.path.join(where, "memory.stat"))
            cache = next((stat[k] for k in keys if k in stat), 0)
            lefts.append(max(limit - max(usage - cache, 0), 0))
    return min(lefts) if lefts else None
