"""Suite-wide set-up: one thread per process when pytest-xdist runs the suite (``-n 2``).

Two xdist workers on a 2-core machine, each with torch's and OpenMP's default of one thread
per core, oversubscribe the cores (measured: 205 s against 111 s with one thread each). Each
worker, and every process a test starts from it (CLI runs, collection workers), uses one.
"""

from __future__ import annotations

import os


def pytest_configure(config):
    """In an xdist worker: one torch / OpenMP thread, for it and for the processes it starts."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)
