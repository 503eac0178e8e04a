"""Running a collection: lock the output folder, plan from the manifest, process, record.

:func:`run_collection` is ``torchiid decompose`` without the printing: the same steps whether
the images are processed in this process, by ``--workers`` processes or on a Dask cluster.

1. take the output folder's lock (:class:`~.lock.OutputLock`);
2. read the manifest once and decide what to skip (:func:`~.manifest.plan`);
3. set up the processing (in this process: the model, the device, the ``--mask`` file; with
   workers: each worker does it and reports it), and stop the run with a one-line
   :class:`~.worker.SetupError` when that fails (nothing is recorded for the images);
4. process the rest, appending one manifest record per image as it ends;
5. on an interrupt, record the images that completed, stop the workers (on Dask: cancel the
   tasks not started, wait up to :data:`~.dask_runner.STOP_GRACE` seconds for the running ones
   and record those that end) and raise :class:`RunInterrupted`; the lock is always released.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from torchiid.collection.lock import OutputLock
from torchiid.collection.manifest import (
    MANIFEST_NAME,
    Manifest,
    ManifestWriter,
    Plan,
    plan,
    record_of,
)
from torchiid.collection.records import ImageJob, ImageResult, InterruptedAfterCommit
from torchiid.collection.settings import RunSettings, params_hash
from torchiid.collection.worker import SetupError, worker_state
from torchiid.io.inputs import InputItem

__all__ = ["Progress", "Reporter", "RunInterrupted", "RunSummary", "run_collection"]


@dataclass
class RunSummary:
    """What a run did.

    Attributes:
        total: inputs named.
        done: images decomposed (or whose complete files were found) in this run.
        failed: images that failed in this run.
        skipped_done: inputs skipped as done before.
        skipped_failed: inputs skipped as failed before (``retry_failed`` retries them).
        retried: images given to a new worker after their worker died.
        seconds: wall time of the processing (after planning).
        plan_seconds: time to read the manifest and decide what to skip.
        hashed: inputs whose SHA-256 had to be computed to decide.
        interrupted_on: images being processed when the run was interrupted (nothing of
            them was written).
        left_running: images whose Dask tasks were still running when the run stopped: their
            tasks are cancelled, but a task already running cannot be stopped and may still
            write the image's files (without a manifest record; a rerun recognises complete
            files, see :func:`~.job.process_image`).
        failures: the failed results of this run.
    """

    total: int = 0
    done: int = 0
    failed: int = 0
    skipped_done: int = 0
    skipped_failed: int = 0
    retried: int = 0
    seconds: float = 0.0
    plan_seconds: float = 0.0
    hashed: int = 0
    interrupted_on: list[str] = field(default_factory=list)
    left_running: list[str] = field(default_factory=list)
    failures: list[ImageResult] = field(default_factory=list)

    @property
    def processed(self) -> int:
        """Images that ended (done or failed) in this run."""
        return self.done + self.failed

    @property
    def all_failed(self) -> int:
        """Inputs without outputs at the end: failed now or before."""
        return self.failed + self.skipped_failed


@dataclass
class Progress:
    """Where a run stands, after each image."""

    processed: int
    to_process: int
    elapsed: float

    @property
    def per_minute(self) -> float:
        """Images per minute so far."""
        return 60.0 * self.processed / self.elapsed if self.elapsed > 0 else 0.0

    @property
    def eta(self) -> float | None:
        """Seconds still needed at the rate so far (``None`` before the first image)."""
        if not self.processed:
            return None
        return (self.to_process - self.processed) * self.elapsed / self.processed


class Reporter(Protocol):
    """What :func:`run_collection` tells its caller."""

    def planned(self, plan: Plan, summary: RunSummary) -> None:
        """The plan is made (before any image)."""

    def result(self, result: ImageResult, progress: Progress) -> None:
        """One image ended."""

    def retrying(self, job: ImageJob, how: str) -> None:
        """The worker process on ``job`` died (``how``); the image is tried again."""

    def compiling(self) -> None:
        """A worker process compiles the CPU kernels (the first run in an environment).

        Optional, like :meth:`retrying`; in this process the caller watches for it itself
        (:func:`~torchiid.core.first_compile.notify_first_compile`).
        """


class RunInterrupted(KeyboardInterrupt):  # noqa: N818 - it is an interrupt
    """The run was interrupted; ``summary`` says what it did before."""

    def __init__(self, summary: RunSummary) -> None:
        super().__init__("interrupted")
        self.summary = summary


def run_collection(
    items: Sequence[InputItem],
    settings: RunSettings,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    retries: int = 1,
    retry_failed: bool = False,
    redo: bool = False,
    decompose_fn: Callable | None = None,
    show_progress: bool = False,
    reporter: Reporter | None = None,
    release_models: bool = False,
) -> RunSummary:
    """Decompose a collection into ``settings.out`` with a manifest (see the module notes).

    Args:
        items: the inputs, with unique keys (:func:`~torchiid.io.inputs.unique_keys`).
        settings: what to compute and write.
        workers: ``None``: in this process; N: N worker processes (:class:`~.pool.WorkerPool`).
        scheduler: a Dask scheduler address (:func:`~.dask_runner.run_on_dask`).
        retries: tries after the first when a worker dies on an image (or, on Dask, when its
            task raises an unexpected error).
        retry_failed: run again the inputs that failed before.
        redo: ignore the manifest: run every input (existing files still need ``overwrite``).
        decompose_fn: the decomposition function (default :func:`torchiid.model.decompose`,
            looked up once there is an image to decompose in this process; for workers and
            Dask a picklable module-level function).
        show_progress: iteration bars of the images processed in this process.
        reporter: told of the plan and of every result.
        release_models: in this process (``workers`` and ``scheduler`` ``None``), give back
            the CNN's memory once the last image's Stage 0 is done, for a process that ends
            with the run (the ``torchiid decompose`` command); a later run loads it again.

    Returns:
        The :class:`RunSummary`.

    Raises:
        RunInterrupted: Ctrl-C, SIGINT or SIGTERM; the images that completed are recorded.
        SetupError: this process or a worker process cannot be set up (the model, the device,
            the ``--mask`` file); the images that completed before are recorded.
        TorchiidError: another run holds the output folder, or the workers or the cluster
            cannot be used.
    """
    summary = RunSummary(total=len(items))
    phash = params_hash(settings)
    lock = OutputLock(settings.out)
    lock.acquire()
    writer = ManifestWriter(os.path.join(settings.out, MANIFEST_NAME), eager=lock.existed)
    results: Iterator[ImageResult] | None = None
    busy: Callable[[], list[ImageJob]] = list
    late: Callable[[], list[ImageResult]] = list
    left: list[ImageJob] = []
    masks = {item.key: item.mask for item in items}

    def record(result: ImageResult) -> None:
        mask = masks.get(result.key)
        writer.append(record_of(result, phash, os.fspath(mask) if mask else None))
        if result.ok:
            summary.done += 1
        else:
            summary.failed += 1
            summary.failures.append(result)

    try:
        _check_manifest_writable(writer.path)
        t0 = time.perf_counter()
        the_plan = plan(
            items,
            Manifest(os.path.join(settings.out, MANIFEST_NAME)),
            phash,
            out=settings.out,
            retry_failed=retry_failed,
            redo=redo,
        )
        summary.plan_seconds = time.perf_counter() - t0
        summary.skipped_done = len(the_plan.done_before)
        summary.skipped_failed = len(the_plan.failed_before)
        summary.hashed = the_plan.hashed
        for refreshed in the_plan.refreshed:  # touched, unchanged: the next rerun is fast
            writer.append(refreshed)
        if reporter is not None:
            reporter.planned(the_plan, summary)
        jobs = the_plan.todo
        if not jobs:
            return summary
        if scheduler is None and workers is None and decompose_fn is None:
            from torchiid import model  # loaded now, when there is work, before the clock starts

            decompose_fn = model.decompose  # looked up now: a caller may have replaced it
        t1 = time.perf_counter()
        if scheduler is not None:
            from torchiid.collection.dask_runner import run_on_dask

            finished: list[ImageResult] = []
            results = run_on_dask(
                jobs,
                settings,
                scheduler,
                retries=retries,
                decompose_fn=decompose_fn,
                late=finished,
                left_running=left,
                on_compiling=getattr(reporter, "compiling", None),
            )
            # on an interrupt, the tasks that ended while it waited are in `finished`; those
            # still running are in `left`: cancelled, but they may still write their files
            late = lambda: finished  # noqa: E731
        elif workers is not None:
            from torchiid.collection.pool import WorkerPool

            pool = WorkerPool(
                workers,
                settings,
                retries=retries,
                decompose_fn=decompose_fn,
                on_retry=getattr(reporter, "retrying", None),
                on_compiling=getattr(reporter, "compiling", None),
            )
            results = pool.run(jobs)
            busy = lambda: pool.busy  # noqa: E731
            late = lambda: pool.late_results  # noqa: E731
        else:
            worker_state(settings)  # a set-up error stops the run before any image
            current: list[ImageJob] = []
            results = _here(
                jobs, settings, decompose_fn, show_progress, phash, current, release_models
            )
            busy = lambda: list(current)  # noqa: E731
        for result in results:
            record(result)
            if result.attempts > 1:
                summary.retried += 1
            if reporter is not None:
                reporter.result(
                    result, Progress(summary.processed, len(jobs), time.perf_counter() - t1)
                )
        summary.seconds = time.perf_counter() - t1
        return summary
    except KeyboardInterrupt as exc:
        if results is not None:
            results.close()  # stops the workers; results that arrive meanwhile are kept
        on = busy()
        if isinstance(exc, InterruptedAfterCommit):
            record(exc.result)
            on = [j for j in on if j.index != exc.result.index]
        for result in late():
            record(result)
            on = [j for j in on if j.index != result.index]
        summary.interrupted_on = [j.path for j in on]
        summary.left_running = [j.path for j in left]
        raise RunInterrupted(summary) from None
    except SetupError:
        for result in late():  # images that completed while the workers stopped
            record(result)
        raise
    finally:
        if results is not None:
            results.close()
        writer.close()
        lock.release()


def _check_manifest_writable(path: Path) -> None:
    """Refuse a run whose manifest is there but cannot be added to, before any image.

    Every finished image is recorded there; without it the files would be written and the run
    would then fail on the record.
    """
    if not path.exists():
        return  # made on the first record, in the folder the lock showed to be writable
    try:
        with open(path, "a", encoding="utf-8"):
            pass
    except OSError as exc:
        raise SetupError(
            f"{path}: cannot be written ({exc.strerror or exc}); the run records every image there"
        ) from None


def _here(
    jobs: Sequence[ImageJob],
    settings: RunSettings,
    decompose_fn: Callable | None,
    show_progress: bool,
    phash: str,
    current: list[ImageJob],
    release_models: bool = False,
) -> Iterator[ImageResult]:
    from torchiid.collection.job import process_image  # the model: only when there is work

    kwargs = {} if decompose_fn is None else {"decompose_fn": decompose_fn}
    for i, job in enumerate(jobs):
        current[:] = [job]
        last = release_models and i == len(jobs) - 1
        result = process_image(
            job, settings, show_progress=show_progress, phash=phash, release_models=last, **kwargs
        )
        current[:] = []
        yield result
