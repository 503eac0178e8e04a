"""Where the compiled kernels apply, and the threads they run on.

The kernels are used only where they apply (:func:`usable`): numba importable, CPU tensors of
float32 or float64, and no autograd graph to record (the differentiable losses keep the torch
ops). ``TORCHIID_KERNELS=torch`` in the environment turns them off, e.g. to compare the two
paths. The first use in a Python environment compiles them (up to a minute on 2 cores, once:
numba caches the machine code on disk for every later process;
:mod:`torchiid.core.first_compile` lets a run say so meanwhile).

Threads: as many as torch uses (``torch.get_num_threads()``). The stencil product runs on
numba's thread pool, one call at a time (numba's fallback threading layer aborts on
concurrent calls); the other kernels split the image's rows into bands and run them at once
on a small Python thread pool (the kernels release the GIL). Small calls and one-thread
processes run on the calling thread only. Each output element is computed by one thread in
a fixed order, so the result does not depend on the number of threads.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from types import ModuleType
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from torchiid.core.first_compile import watch_compilation

__all__ = [
    "PARALLEL_WORK",
    "bands",
    "compiled",
    "executor",
    "kernel_module",
    "offset_arrays",
    "parallel_lock",
    "run_bands",
    "usable",
]

logger = logging.getLogger("torchiid.priors.kernels")

#: below this many multiply-adds a call runs on the calling thread only: handing bands to
#: the pool costs more than it saves
PARALLEL_WORK = 1 << 21

#: one caller at a time on numba's pool: its fallback threading layer (workqueue, where
#: neither OpenMP nor TBB is available) aborts the process on concurrent parallel calls
parallel_lock = threading.Lock()

_pool_lock = threading.Lock()
_pool: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, workers, pool)


@cache
def compiled() -> tuple[ModuleType, ModuleType] | None:
    """``(numba, the kernel module)``; ``None`` without numba or with ``TORCHIID_KERNELS=torch``."""
    choice = os.environ.get("TORCHIID_KERNELS", "").strip().lower()
    if choice == "torch":
        return None
    if choice not in ("", "numba"):
        logger.warning(
            "TORCHIID_KERNELS=%s is neither torch nor numba: using the compiled (numba) kernels",
            os.environ["TORCHIID_KERNELS"],
        )
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; kept for slim installs
        return None
    watch_compilation()  # before the first kernel: a compilation is said while it runs
    try:
        from torchiid.priors import stencil_kernels
    except Exception as exc:  # pragma: no cover - e.g. no writable directory for numba's cache
        logger.warning("compiled kernels unavailable (%s); using the torch ops", exc)
        return None
    return numba, stencil_kernels


def kernel_module() -> Any:
    """The kernel module (callers check :func:`usable` first)."""
    found = compiled()
    if found is None:
        raise RuntimeError("the compiled kernels are not available (see kernels.usable)")
    return found[1]


def usable(*tensors: torch.Tensor, offsets: list[tuple[int, int]] | None = None) -> bool:
    """Whether the compiled kernels apply to these tensors (see the module notes).

    With ``offsets``, also whether they are half offsets (``dy >= 0``), the only ones the
    kernels handle (:func:`~torchiid.priors.stencil.half_offsets` gives such).
    """
    if compiled() is None:
        return False
    if offsets is not None and any(dy < 0 for dy, _ in offsets):
        return False
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64):
        return False
    grad = torch.is_grad_enabled()
    return all(
        t.device.type == "cpu" and t.dtype == dtype and not (grad and t.requires_grad)
        for t in tensors
    )


@cache
def offset_arrays(
    offsets: tuple[tuple[int, int], ...],
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The offsets' ``dy`` and ``dx`` as contiguous int64 arrays (cached per stencil)."""
    arr = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    return np.ascontiguousarray(arr[:, 0]), np.ascontiguousarray(arr[:, 1])


def executor(workers: int) -> ThreadPoolExecutor:
    """The process's band pool with at least ``workers`` threads (a new one after a fork)."""
    global _pool
    with _pool_lock:
        if _pool is None or _pool[0] != os.getpid() or _pool[1] < workers:
            if _pool is not None and _pool[0] == os.getpid():
                _pool[2].shutdown(wait=False)  # a smaller pool: let its threads end
            _pool = (os.getpid(), workers, ThreadPoolExecutor(workers, "torchiid-kernel"))
        return _pool[2]


def run_bands(kernel: Callable[..., Any], args: tuple[Any, ...], cuts: list[int]) -> None:
    """``kernel(*args, cuts[i], cuts[i + 1])`` for every band ``i``, the first on this thread."""
    n = len(cuts) - 1
    if n == 1:
        kernel(*args, cuts[0], cuts[1])
        return
    pool = executor(n - 1)
    futures = [pool.submit(kernel, *args, cuts[i], cuts[i + 1]) for i in range(1, n)]
    kernel(*args, cuts[0], cuts[1])
    for f in futures:
        f.result()


def bands(units: int, work: int) -> list[int]:
    """Cuts of ``units`` rows (or blocks) into torch's thread count of bands (one when small)."""
    n = min(torch.get_num_threads(), units)
    if n <= 1 or work < PARALLEL_WORK:
        n = 1
    return [units * i // n for i in range(n + 1)]
