"""Suite-wide set-up: Ctrl-C that can be delivered, and one thread per xdist worker.

* A shell that starts the suite in the background (``nohup ... &``, some CI runners) leaves
  SIGINT ignored, and every process inherits that, so the tests of Ctrl-C (interrupted runs,
  workers, video frames) could not interrupt anything. The suite restores Python's default
  handler; the processes it starts then get the default disposition too.
* Two xdist workers (``-n 2``) on a 2-core machine, each with torch's and OpenMP's default of
  one thread per core, oversubscribe the cores (measured: 205 s against 111 s with one thread
  each). Each worker, and every process a test starts from it (CLI runs, collection workers),
  uses one.
* ``counting_os``: the disk-scaling tests of the input lister and the collection manifest count
  the ``os`` calls a pass makes instead of timing it, so their checks do not depend on load.
* The browser app (``torchiid/app``) imports Gradio, which only the ``app`` extra installs:
  without it, its modules are not collected for their doctests (``tests/app`` skips itself).
"""

from __future__ import annotations

import importlib.util
import os
import signal

import pytest

collect_ignore = [] if importlib.util.find_spec("gradio") else ["torchiid/app"]


def pytest_configure(config):
    """Deliverable SIGINT; in an xdist worker, one torch / OpenMP thread."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)


class CountingOs:
    """A stand-in for the ``os`` module that counts the calls named in ``counted``."""

    def __init__(self, counted):
        self.calls = dict.fromkeys(counted, 0)

    def __getattr__(self, name):
        real = getattr(os, name)
        if name not in self.calls:
            return real

        def counted(*args, **kwargs):
            self.calls[name] += 1
            return real(*args, **kwargs)

        return counted


@pytest.fixture
def counting_os():
    """``counting_os(*names)``: a :class:`CountingOs` counting the calls ``names``."""
    return lambda *names: CountingOs(names)
