"""Helpers of the collection tests, imported by name (``from collection_helpers import ...``).

They live outside ``conftest.py``: several test folders have a ``conftest.py``, and a test
module that imported one of them by name would make the others collide with it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from skimage import data

#: options of a fast run (the tests are about the orchestration, not the method)
FAST = ["--method", "retinex", "--no-progress"]


def photo(path: Path, seed: int = 0, w: int = 80, h: int = 64) -> Path:
    """A small real photo (a crop of skimage's chelsea, shifted by ``seed``) as PNG."""
    img = data.chelsea()[40 + 7 * seed : 40 + 7 * seed + 2 * h, 60 : 60 + 2 * w]
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)[..., ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(img))
    return path


def decompose_counting_arenas(image, params, **kwargs):
    """:func:`torchiid.model.decompose`, after writing how many malloc arenas the process has.

    A worker's decomposition for the pool tests: a new thread allocates first (glibc gives
    it an arena of its own unless the process shares one), then glibc's ``malloc_stats``
    (one ``Arena N:`` block per arena, on stderr) goes to ``$TORCHIID_TEST_ARENAS``.
    """
    import ctypes
    import os
    import threading

    from torchiid.model import decompose

    def work() -> None:
        blocks = [bytearray(200_000) for _ in range(8)]  # malloc'd, below the mmap threshold
        del blocks

    t = threading.Thread(target=work)
    t.start()
    t.join()
    fd = os.open(os.environ["TORCHIID_TEST_ARENAS"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    saved = os.dup(2)
    try:
        os.dup2(fd, 2)
        ctypes.CDLL(None).malloc_stats()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(fd)
    return decompose(image, params, **kwargs)


def decompose_compiling_a_kernel(image, params, **kwargs):
    """:func:`torchiid.model.decompose`, after compiling a kernel of torchiid's, as on a first run.

    A worker's decomposition for the pool tests: the kernel (``x + 1``, defined in a module
    named like torchiid's) is not cached, so numba compiles it in every worker.
    """
    from numba import njit

    from torchiid.model import decompose
    from torchiid.priors.kernel_runtime import compiled

    compiled()  # what torchiid does before its first kernel
    namespace = {"__name__": "torchiid.worker_probe"}
    exec("def one(x):\n    return x + 1\n", namespace)
    njit(namespace["one"])(1)
    return decompose(image, params, **kwargs)


class CompileCounter:
    """A run's reporter that counts how often it is told that the kernels compile."""

    compiled = 0

    def planned(self, plan, summary):
        """Nothing to do with the plan."""

    def result(self, result, progress):
        """Nothing to do with a result."""

    def compiling(self):
        """Count one."""
        self.compiled += 1
