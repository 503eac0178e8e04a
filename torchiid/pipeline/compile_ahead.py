"""Stage 2's kernels compiled in a second process while a first run compiles the rest.

The first run in a Python environment compiles the CPU kernels one after the other, each on
its first call (:mod:`torchiid.core.first_compile`), and numba compiles on one core: on a
2-core machine the other core waits. The reflectance stage's kernels (the Bregman update and
its halos, the colour affinity, the proposals' factor) take about 40% of the compilation and
are first called only after Stage 0 and the first shading solve, whose own kernels compile
before them. :class:`CompileAhead` starts this module as a second process
(``python -m torchiid.pipeline.compile_ahead``) at the first compilation of a run: it runs
Stage 2's first two alternations on a small synthetic problem with the run's parameters and
thread count, so numba compiles the same kernels, with the same signatures, into the same
cache; when the run reaches Stage 2 it loads them from there. Only the machine code is
shared: the helper's results are thrown away, and a kernel the helper has not finished when
the run needs it is compiled by the run as before. numba puts each cache file in place whole
(the workers of ``--workers N`` also compile side by side into one cache); two processes
that add entries to one kernel's index at the same moment may lose one of them, which costs a
later run that kernel's compilation, nothing else.

The helper runs at a lower priority (``nice``), writes nothing but numba's cache and is
stopped when the run ends (:meth:`CompileAhead.close`); if the run dies without stopping it
(``kill -9``), the helper notices that its parent is gone and exits. It is not started when
the run uses one thread (``--threads 1``: the other cores are not the run's to take), for
parameters that never run Stage 2 (``--variant baseline1``), or with
``TORCHIID_COMPILE_AHEAD=0`` in the environment; the ``torchiid`` commands (``torchiid app``
among them) also leave it out of a run on a GPU, whose solves use no CPU kernels, and of
commands without Stage 2 (``features``). The workers of ``--workers N`` and of a Dask cluster
compile on their own. A Python program that calls :func:`torchiid.decompose` compiles in its
own process only, unless it wraps the call as in :func:`compiling_ahead`'s example.

Importing this module loads neither torch nor numba.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchiid.params import Parameters

__all__ = ["ENVIRONMENT_VARIABLE", "CompileAhead", "compile_stage2", "compiling_ahead"]

logger = logging.getLogger("torchiid")

#: ``TORCHIID_COMPILE_AHEAD=0`` keeps a first run's compilation in its own process
ENVIRONMENT_VARIABLE = "TORCHIID_COMPILE_AHEAD"

#: the helper's priority below the run's (``os.nice`` increment)
NICENESS = 10

#: seconds between the helper's checks that the run that started it still runs
PARENT_CHECK = 0.5

#: the synthetic problem's size (at least the patch size a side, which a decomposition needs):
#: solved in milliseconds once the kernels are compiled
HEIGHT, WIDTH = 64, 96


def _enabled() -> bool:
    return os.environ.get(ENVIRONMENT_VARIABLE, "1").strip().lower() not in ("0", "no", "false")


class CompileAhead:
    """The second process of a first run, started at most once (see the module notes).

    Args:
        params: the run's parameters, or a function that gives them when the helper starts
            (``None``: the ``default`` preset).
        threads: the run's CPU threads (``None``: ``torch.get_num_threads()`` when the helper
            starts); the helper uses as many, so numba compiles the same kernel variants.

    Attributes:
        process: the helper's :class:`subprocess.Popen`, or ``None`` if none was started.
    """

    def __init__(
        self,
        params: Parameters | Callable[[], Parameters | None] | None = None,
        threads: int | None = None,
    ) -> None:
        self._params = params
        self._threads = threads
        self._tried = False
        self._lock = threading.Lock()  # start (a compiling thread) against close (the run's)
        self.process: subprocess.Popen[bytes] | None = None

    def parameters(self) -> Parameters | None:
        """The parameters the helper compiles for (``None``: the ``default`` preset)."""
        return self._params() if callable(self._params) else self._params

    def command(self) -> list[str] | None:
        """The helper's command line, or ``None`` where none should run (see the notes)."""
        if not _enabled():
            return None
        threads = self._threads
        if threads is None:
            import torch

            threads = torch.get_num_threads()
        if threads < 2:
            return None
        params = self.parameters()
        if params is not None and not any(
            params.alternation(k)[1].active for k in range(1, params.iterations + 1)
        ):
            return None  # Stage 2 never runs: nothing of the helper's would be loaded
        cmd = [sys.executable, "-m", __name__, "--threads", str(threads)]
        cmd += ["--parent", str(os.getpid())]
        if params is not None:
            cmd += ["--params", json.dumps(params.to_dict())]
        return cmd

    def start(self) -> bool:
        """Start the helper unless it was started (or refused) before; whether it was started.

        Never raises: a helper that cannot start leaves the run compiling on its own, as
        without it (logged at debug level). After :meth:`close` nothing starts.
        """
        with self._lock:
            if self._tried:
                return self.process is not None
            self._tried = True
            try:
                cmd = self.command()
                if cmd is None:
                    return False
                proc = subprocess.Popen(
                    cmd,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    close_fds=True,
                )
            except Exception:  # noqa: BLE001 - an optimisation of a first run, never its failure
                logger.debug("the kernels' second compiling process did not start", exc_info=True)
                return False
            self.process = proc
        # reaped as soon as it ends, not only at close (the app runs for hours)
        threading.Thread(target=proc.wait, name="torchiid-compile-ahead", daemon=True).start()
        return True

    def close(self, timeout: float = 2.0) -> None:
        """Stop the helper if it still runs (the kernels it finished stay in the cache).

        A :meth:`start` after this starts nothing.
        """
        with self._lock:
            self._tried = True
            proc = self.process
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextmanager
def compiling_ahead(
    params: Parameters | Callable[[], Parameters | None] | None = None,
    threads: int | None = None,
) -> Iterator[CompileAhead]:
    """A :class:`CompileAhead` for a run, closed when the block ends.

    Example:
        >>> from torchiid.core.first_compile import notify_first_compile
        >>> from torchiid.pipeline.compile_ahead import compiling_ahead
        >>> with compiling_ahead() as ahead, notify_first_compile(ahead.start):
        ...     pass  # e.g. torchiid.decompose(image)
    """
    ahead = CompileAhead(params, threads)
    try:
        yield ahead
    finally:
        ahead.close()


def compile_stage2(params: Parameters | None = None) -> None:
    """Run Stage 2's first two alternations on a small synthetic problem (this process).

    The problem has what the reflectance stage's priors read (a ``ρ``, proposal features
    ``g̊`` and segments) in float32 on the CPU, as a photo's has: every kernel of Stage 2
    that the parameters use is called, in a cold and in a warm-started solve.
    """
    import torch

    from torchiid.features.semantic import SemanticFeatures
    from torchiid.params import Parameters
    from torchiid.pipeline.alternation import Alternation
    from torchiid.pipeline.inputs import working_inputs

    p = (params or Parameters()).replace(max_side=0)
    h = max(HEIGHT, p.features.patch_size)
    w = max(WIDTH, h)
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(1, 3, h, w, generator=gen) * 0.8 + 0.1
    work = working_inputs(
        image, None, p, init=None, temporal=None, schedule_start=1,
        return_stage1=False, return_iterations=False,
    )  # fmt: skip
    dim = p.features.proposal_pca_dim
    gpca = torch.rand(1, dim, h, w, generator=gen)
    segments = torch.arange(h * w).view(1, h, w) * 8 // (h * w)  # eight bands of rows
    features = SemanticFeatures(None, None, None, gpca, segments)
    run = Alternation(work, features, p)
    run.rho = work.image
    for k in (1, 2):
        run.reflectance_step(k, p.alternation(k)[1])


def main(argv: list[str] | None = None) -> int:
    """The helper process (:func:`compile_stage2` at a lower priority).

    ``python -m torchiid.pipeline.compile_ahead [--threads N] [--params JSON] [--parent PID]``
    """
    ap = argparse.ArgumentParser(prog="python -m torchiid.pipeline.compile_ahead")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--params", help="the run's parameters as JSON text")
    ap.add_argument("--parent", type=int, default=0, help="the run's process id (0: none)")
    args = ap.parse_args(argv)
    if hasattr(os, "nice"):
        try:
            os.nice(NICENESS)
        except OSError:  # pragma: no cover - not allowed here: run at the same priority
            pass
    if args.parent:
        _exit_with(args.parent)
    import torch

    from torchiid.params import Parameters

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    params = None
    if args.params:
        params = Parameters.from_dict(json.loads(args.params))
    with torch.no_grad():
        compile_stage2(params)
    return 0


def _exit_with(parent: int) -> None:
    """End this process once ``parent`` is no longer its parent (it has ended).

    A run stops its helper as it ends; a run killed outright cannot, and a helper left
    compiling would take a core from whatever runs next. The run's process id comes from
    the run itself: one that ended before the helper got this far is caught at once.
    """

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK)
        os._exit(0)

    threading.Thread(target=watch, name="torchiid-parent-watch", daemon=True).start()


if __name__ == "__main__":
    sys.exit(main())
