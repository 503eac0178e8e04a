"""``--workers N``: N worker processes on this machine, each with its share of the cores.

The workers are started with the ``spawn`` method (``fork`` after torch has started its thread
pools is unsafe), with ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS`` and ``OPENBLAS_NUM_THREADS``
set in their environment before anything is imported, and ``torch.set_num_threads`` called
before the first image. Each worker loads the model once (:func:`~.worker.worker_state`) and then
takes one image at a time over its own pipe, so the parent always knows which image each
worker is on. When a worker dies (killed, out of memory, a crash in native code), only that
image is lost: its temporary files are removed, it is given to a new worker again (``retries``
times, default once) and the other workers go on undisturbed.

An interrupt of the run (Ctrl-C reaches every process of the terminal's group; SIGTERM to the
parent is passed on to the workers) stops each worker in its image: the image's temporary files
are removed (an image whose files were being put in place completes and is reported), and the
parent records the results that arrive, then returns. A worker still running after
:data:`STOP_GRACE` seconds is killed; the parent then removes its image's temporary files and
the folders that did not exist before that image and are empty. Only a signal to the parent
ends the run: a worker stopped by a signal of its own (SIGTERM or SIGINT to that process alone)
is a worker that died; its image is given to a new worker like any other. A parent that ignores
SIGINT (a job that a shell starts in the background) starts workers that ignore it too.

A worker that cannot be set up (:func:`~.worker.worker_state`: the model, the device, the
``--mask`` file) says so before it takes an image, and the run stops with that
:class:`~.worker.SetupError`: every worker would fail the same way, and a bad model is not a bad
input.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import os
import re
import shutil
import signal
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any

from torchiid.collection.job import (
    ImageJob,
    ImageResult,
    InterruptedAfterCommit,
    process_image,
    with_attempt,
)
from torchiid.collection.settings import RunSettings
from torchiid.collection.worker import SetupError, worker_state
from torchiid.core.exceptions import TorchiidError
from torchiid.core.first_compile import COMPILING, notify_first_compile
from torchiid.core.memory import share_one_malloc_arena
from torchiid.io.output_set import missing_folders, remove_empty_folders

__all__ = ["WorkerPool", "available_cores", "remove_temporary_sets"]

log = logging.getLogger("torchiid")

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

#: seconds the workers get to stop after an interrupt before they are killed
STOP_GRACE = 20.0


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def remove_temporary_sets(folder: Path, stem: str | None = None) -> int:
    """Remove the temporary folders of output sets left in ``folder`` by dead processes.

    Only folders named like :class:`~torchiid.io.layers.OutputSet`'s
    (``.torchiid-<stem>-<8 random characters>``), of ``stem`` when given. Call it only when no
    live process can be writing that set. Returns how many were removed.
    """
    label = re.escape(stem) if stem is not None else ".+"
    pattern = re.compile(rf"\.torchiid-{label}-[a-z0-9_]{{8}}")
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return 0
    for entry in entries:
        if pattern.fullmatch(entry.name) and entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)
            removed += 1
    return removed


_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def _worker_main(
    conn, settings: RunSettings, decompose_fn: Callable | None, ignore_sigint: bool = False
) -> None:
    """A worker process: warm up, then process the images the parent sends, one at a time.

    It starts with SIGINT and SIGTERM blocked (see :meth:`WorkerPool._start`), so that an
    interrupt during the start-up imports waits until here; both then raise
    ``KeyboardInterrupt``, which ends the worker after telling the parent which signal it was
    (the first one only: Ctrl-C to the group and the parent's SIGTERM often both arrive, and
    the second must not interrupt the removal of the image's temporary files). With
    ``ignore_sigint`` (the parent ignores SIGINT, as a job started in the background by a
    shell does) the worker ignores it too.
    """
    received: list[str] = []

    def terminate(signum, frame):
        received.append(signal.Signals(signum).name)
        if len(received) == 1:  # a second signal must not break off the clean-up
            raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, terminate)
    signal.signal(signal.SIGINT, signal.SIG_IGN if ignore_sigint else terminate)
    logging.basicConfig(level=logging.WARNING, format="torchiid: %(message)s")
    kwargs = {} if decompose_fn is None else {"decompose_fn": decompose_fn}
    sending = threading.Lock()  # the kernels may compile on another thread of the worker

    def send(message: tuple) -> None:
        with sending:
            conn.send(message)

    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _SIGNALS)
        share_one_malloc_arena()  # a process of the pool's own, as the command line's
        try:
            worker_state(settings)
        except SetupError as exc:  # the parent stops the run: no image could be processed
            send(("setup_failed", str(exc)))
            return
        send(("ready", os.getpid()))
        with notify_first_compile(lambda: send(("compiling", os.getpid()))):
            while True:
                job = conn.recv()
                if job is None:
                    break
                try:
                    result = process_image(job, settings, **kwargs)
                except InterruptedAfterCommit as done:
                    send(("result", done.result))
                    break
                send(("result", result))
    except KeyboardInterrupt:
        with contextlib.suppress(Exception):
            send(("interrupted", received[-1] if received else "SIGINT"))
    except (EOFError, BrokenPipeError, ConnectionResetError):
        pass
    finally:
        signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)  # the exit is not interrupted
        with contextlib.suppress(OSError):
            conn.close()


@contextlib.contextmanager
def _thread_environment(threads: int):
    """``OMP_NUM_THREADS`` etc. set for the processes started in the block."""
    before = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@dataclass
class _Worker:
    process: Any
    conn: Any
    job: ImageJob | None = None
    ready: bool = False
    started_jobs: int = 0
    stopping: bool = False
    interrupted: str | None = None  # the signal that stopped it, when it was not the run's
    log: list = field(default_factory=list)


def _death(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"killed by {name}"
    return f"exit status {exitcode}"


class WorkerPool:
    """N spawned worker processes that each process one image at a time.

    Args:
        workers: how many processes.
        settings: the run's settings; ``settings.threads`` is each worker's torch thread count
            (also set as ``OMP_NUM_THREADS`` etc. in its environment).
        retries: how many more times an image is tried when its worker dies on it.
        decompose_fn: the decomposition function (picklable: a module-level function);
            ``None``: :func:`torchiid.model.decompose`.
        on_retry: called with the image and how its worker died, before it is tried again.
        on_compiling: called once, when the first worker starts compiling the CPU kernels
            (:mod:`torchiid.core.first_compile`: the first run in a Python environment).
    """

    def __init__(
        self,
        workers: int,
        settings: RunSettings,
        *,
        retries: int = 1,
        decompose_fn: Callable | None = None,
        on_retry: Callable[[ImageJob, str], None] | None = None,
        on_compiling: Callable[[], None] | None = None,
    ) -> None:
        if workers < 1:
            raise TorchiidError(f"--workers must be >= 1, got {workers}")
        self.n = workers
        self.threads = settings.threads or max(1, available_cores() // workers)
        self.settings = dataclasses.replace(settings, threads=self.threads)
        self.retries = retries
        self.decompose_fn = decompose_fn
        self.on_retry = on_retry
        self.on_compiling = on_compiling
        self._compiling_said = False
        self._ctx = multiprocessing.get_context("spawn")
        self._workers: list[_Worker] = []
        self.deaths = 0
        self._early_deaths = 0
        self.stopped_on: list[ImageJob] | None = None
        self.late_results: list[ImageResult] = []
        self._new_folders: dict[int, list[Path]] = {}  # per image: its folders missing at first

    @property
    def busy(self) -> list[ImageJob]:
        """The images the workers are on (after an interrupt: those they were stopped on)."""
        if self.stopped_on is not None:
            return list(self.stopped_on)
        return [w.job for w in self._workers if w.job is not None]

    def _start(self) -> _Worker:
        parent, child = self._ctx.Pipe()
        ignore_sigint = signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        process = self._ctx.Process(
            target=_worker_main,
            args=(child, self.settings, self.decompose_fn, ignore_sigint),
            name="torchiid-worker",
            daemon=True,
        )
        old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)  # inherited: see above
        # The mask alone does not keep Ctrl-C out of a worker's start-up imports: a library
        # thread with SIGINT unblocked can take it, and Python then raises KeyboardInterrupt in
        # the importing main thread. An ignored SIGINT survives exec and
        # Python keeps it ignored at start-up, until _worker_main installs its handler; the
        # parent goes without a SIGINT handler only for the fork and exec.
        main = threading.current_thread() is threading.main_thread()
        old_int = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            with _thread_environment(self.threads):
                process.start()
        finally:
            if main:
                signal.signal(signal.SIGINT, signal.SIG_DFL if old_int is None else old_int)
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        child.close()
        worker = _Worker(process, parent)
        self._workers.append(worker)
        return worker

    def run(self, jobs: Iterable[ImageJob]) -> Iterator[ImageResult]:
        """Process the jobs; yields each image's result as it ends (any order).

        Raises:
            KeyboardInterrupt: interrupted (the workers are stopped first; results that
                arrived while they stopped are in :attr:`late_results`).
            SetupError: a worker process cannot be set up (the workers are stopped first).
            TorchiidError: the worker processes die before they can take an image.
        """
        queue = deque(jobs)
        pending = len(queue)
        try:
            for _ in range(min(self.n, pending)):
                self._start()
            while pending:
                waitables = {}
                for w in self._workers:
                    waitables[w.conn] = w
                    waitables[w.process.sentinel] = w
                handled: set[int] = set()
                for ready in wait(list(waitables)):
                    w = waitables[ready]
                    if id(w) in handled or w not in self._workers:
                        continue  # already handled through its other handle
                    handled.add(id(w))
                    messages = []
                    try:  # what it sent before it exited counts first
                        while w.conn.poll(0):
                            messages.append(w.conn.recv())
                    except (EOFError, OSError):
                        pass
                    for kind, payload in messages:
                        if kind == "setup_failed":
                            raise SetupError(f"a worker process {payload}")
                        if kind == "interrupted":
                            # a signal to the run reaches this process too, and it stops here
                            # first: this one was for the worker alone, which now ends
                            w.interrupted = payload
                        elif kind == "result":
                            w.job = None
                            pending -= 1
                            self._new_folders.pop(payload.index, None)
                            yield payload
                        elif kind == "compiling":
                            self._compiling()
                        else:
                            w.ready = True
                    if not messages or w.interrupted or not w.process.is_alive():
                        if w.process.is_alive() and not w.conn.closed and not w.interrupted:
                            continue
                        result = self._died(w, queue)
                        if result is not None:
                            pending -= 1
                            yield result
                        if queue and len(self._workers) < self.n:
                            self._start()
                        continue
                    if w.job is None:
                        self._give(w, queue)
        except BaseException:
            self._stop_all()
            raise
        self._stop_all()

    def _compiling(self) -> None:
        """A worker compiles the kernels: said once, whichever worker it is."""
        if self._compiling_said:
            return
        self._compiling_said = True
        if self.on_compiling is not None:
            self.on_compiling()
        else:
            log.info("%s", COMPILING)

    def _folder(self, job: ImageJob) -> Path:
        return Path(self.settings.out, job.folder) if job.folder else Path(self.settings.out)

    def _give(self, w: _Worker, queue: deque) -> None:
        if queue:
            w.job = queue.popleft()
            self._new_folders.setdefault(w.job.index, missing_folders(self._folder(w.job)))
            w.started_jobs += 1
            w.conn.send(w.job)
        else:
            with contextlib.suppress(OSError):
                w.conn.send(None)
            w.stopping = True

    def _died(self, w: _Worker, queue: deque) -> ImageResult | None:
        """Handle a worker that exited; returns the result of its image if that is final."""
        w.process.join(timeout=5)
        self._workers.remove(w)
        with contextlib.suppress(OSError):
            w.conn.close()
        job = w.job
        if job is None:
            if not w.stopping and not w.started_jobs:
                self._early_deaths += 1
                if self._early_deaths >= 3 * self.n:
                    raise TorchiidError(
                        "the worker processes die before they take an image "
                        f"({_death(w.process.exitcode)}); run without --workers (workers=None "
                        "in Python) to see why. A Python script that starts workers must "
                        "do it under 'if __name__ == \"__main__\":', since each worker "
                        "imports the script again"
                    )
            return None
        self.deaths += 1
        how = f"stopped by {w.interrupted}" if w.interrupted else _death(w.process.exitcode)
        remove_temporary_sets(self._folder(job), job.stem)
        if job.attempt <= self.retries:
            if self.on_retry is not None:
                self.on_retry(job, how)
            else:
                log.warning("%s: its worker process died (%s); trying it again", job.path, how)
            queue.appendleft(with_attempt(job, job.attempt + 1))
            return None
        attempts = job.attempt
        remove_empty_folders(self._new_folders.pop(job.index, []))
        return ImageResult(
            job.index,
            job.key,
            job.path,
            "failed",
            message=f"{job.path}: the worker process died while processing it ({how}), "
            f"{attempts} time(s)",
            attempts=attempts,
            worker=f"pid {w.process.pid}",
            failure="worker",
        )

    def _stop_all(self) -> None:
        """Stop every worker (SIGTERM to those on an image), then reap them."""
        for w in self._workers:
            if w.process.is_alive():
                if w.job is not None:
                    with contextlib.suppress(OSError):
                        os.kill(w.process.pid, signal.SIGTERM)
                else:
                    with contextlib.suppress(OSError):
                        w.conn.send(None)
        self.stopped_on = [w.job for w in self._workers if w.job is not None]
        for w in self._workers:
            w.process.join(timeout=STOP_GRACE)
            while True:  # an image that completed while it stopped is reported
                try:
                    if not w.conn.poll(0):
                        break
                    kind, payload = w.conn.recv()
                except (EOFError, OSError):
                    break
                if kind == "result":
                    self.late_results.append(payload)
                    self.stopped_on = [j for j in self.stopped_on if j.index != payload.index]
            if w.process.is_alive():
                w.process.kill()
                w.process.join(timeout=5)
            with contextlib.suppress(OSError):
                w.conn.close()
        self._workers = []
        # A worker removes what it wrote of its image when it stops, unless it is killed first
        # (it did not stop within STOP_GRACE): every worker has exited, so nothing can be
        # writing there now. A folder goes only if it did not exist before the image and is
        # empty.
        for job in self.stopped_on:
            remove_temporary_sets(self._folder(job), job.stem)
            remove_empty_folders(self._new_folders.pop(job.index, []))
