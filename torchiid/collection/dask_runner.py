"""``--dask-scheduler ADDRESS``: the images as tasks of an existing ``dask.distributed`` cluster.

Each image is one task (:func:`dask_task`) submitted with ``retries=``; the worker that runs it
loads the model once (:func:`~.worker.worker_state`, cached in the worker process), decomposes
the image and puts its files in place itself, through the same output sets as a local run
(so the output folder must be on a file system that every worker sees under the same path, as
must the inputs). The client appends the manifest as the tasks end (``as_completed``).

Failures: a bad input is a result, not an error (no retry: it would fail again). A task that
raises something unexpected (not a :class:`TorchiidError`: a ``MemoryError``, a bug) is tried
again up to ``retries`` times, maybe on another worker. A task whose worker dies is re-run by
the scheduler on another worker; one that has killed ``distributed.scheduler.allowed-failures``
workers (default 3) ends as ``KilledWorker`` and is recorded as failed. Temporary files of
killed workers are removed at the end of the run. A worker that cannot be set up (the model,
the device, the ``--mask`` file where it runs) fails the image as ``"error"``: retried, and
tried again by a rerun.

Interrupts: Dask cannot stop a task that is running (cancelling it only makes the scheduler
forget it; the worker's thread goes on and writes the image's files). So on Ctrl-C or SIGTERM
the client cancels the tasks not started yet, then waits up to :data:`STOP_GRACE` seconds (a
second Ctrl-C stops waiting) for the running ones and records those that end; any still running
after that are cancelled too and named (``left_running``): they may still write their files,
without a manifest record, and a rerun recognises complete files as done.

``distributed`` is an optional dependency: ``pip install 'torchiid[dask]'``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import secrets
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from torchiid.collection.job import ImageJob, ImageResult, error_message, process_image
from torchiid.collection.pool import remove_temporary_sets
from torchiid.collection.settings import RunSettings, params_hash
from torchiid.core.exceptions import TorchiidError
from torchiid.core.first_compile import COMPILING, notify_first_compile

__all__ = ["ImageTaskError", "dask_task", "run_on_dask"]

log = logging.getLogger("torchiid")

#: seconds to wait for the scheduler
CONNECT_TIMEOUT = 20.0

#: seconds an interrupted run waits for the tasks that are running
STOP_GRACE = 30.0


class ImageTaskError(RuntimeError):
    """An image's task failed for a reason that may not recur (Dask retries it)."""


def dask_task(
    job: ImageJob,
    settings: RunSettings,
    phash: str,
    decompose_fn: Callable | None = None,
    topic: str | None = None,
) -> ImageResult:
    """One image on a Dask worker (see the module notes); raises to be retried.

    With ``topic``, a worker that compiles the CPU kernels for it (the first run in its Python
    environment) logs an event of that topic on the cluster (``Worker.log_event``).
    """
    kwargs = {} if decompose_fn is None else {"decompose_fn": decompose_fn}
    with notify_first_compile(lambda: _log_compiling(topic)):
        result = process_image(job, settings, phash=phash, **kwargs)
    if result.retryable:
        raise ImageTaskError(result.message)
    return result


def _log_compiling(topic: str | None) -> None:
    if topic is None:
        return
    from distributed import get_worker

    with contextlib.suppress(ValueError):  # not on a worker (a task run by hand)
        worker = get_worker()
        worker.log_event(topic, {"worker": worker.address, "pid": os.getpid()})


def _client(address: str, timeout: float):
    try:
        from distributed import Client
    except ImportError:
        raise TorchiidError(
            "--dask-scheduler needs the 'distributed' package: pip install 'torchiid[dask]'"
        ) from None
    try:
        return Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        raise TorchiidError(
            f"cannot reach the Dask scheduler at {address} ({' '.join(str(exc).split())})"
        ) from None


def run_on_dask(
    jobs: Sequence[ImageJob],
    settings: RunSettings,
    address: str,
    *,
    retries: int = 1,
    decompose_fn: Callable | None = None,
    connect_timeout: float | None = None,
    in_flight: list | None = None,
    late: list | None = None,
    left_running: list | None = None,
    on_compiling: Callable[[], None] | None = None,
) -> Iterator[ImageResult]:
    """Run the jobs on the cluster of ``address``; yields each result as its task ends.

    Args:
        jobs: the images.
        settings: the run's settings (``settings.out`` an absolute path the workers see).
        address: the scheduler, e.g. ``tcp://10.0.0.1:8786``.
        retries: Dask ``retries=`` of each task.
        decompose_fn: a picklable decomposition function (default
            :func:`torchiid.model.decompose`).
        connect_timeout: seconds to wait for the scheduler (default :data:`CONNECT_TIMEOUT`).
        in_flight: filled with the jobs not finished yet.
        late: when the generator is interrupted or closed early, filled with the results of
            the tasks that ended while it waited for the running ones (see the module notes).
        left_running: then filled with the jobs whose tasks were still running after
            :data:`STOP_GRACE` seconds (cancelled; they may still write their files).
        on_compiling: called once (on a thread of the client), when a worker first starts
            compiling the CPU kernels for this run's tasks (the first run in its Python
            environment, :mod:`torchiid.core.first_compile`).

    Raises:
        TorchiidError: ``distributed`` is not installed or the scheduler cannot be reached.
    """
    from distributed import as_completed

    client = _client(address, CONNECT_TIMEOUT if connect_timeout is None else connect_timeout)
    phash = params_hash(settings)
    token = secrets.token_hex(4)
    topic = f"torchiid-{token}-compiling"
    said = threading.Event()

    def compiling(event: object) -> None:
        if not said.is_set():
            said.set()
            if on_compiling is not None:
                on_compiling()
            else:
                log.info("a worker: %s", COMPILING)

    futures = {}
    try:
        client.subscribe_topic(topic, compiling)
        for job in jobs:
            job = dataclasses.replace(  # the workers may run in another folder, or elsewhere
                job,
                path=os.path.abspath(job.path),
                mask=None if job.mask is None else os.path.abspath(job.mask),
            )
            future = client.submit(
                dask_task,
                job,
                settings,
                phash,
                decompose_fn,
                topic,
                key=f"torchiid-{token}-{job.index}",
                retries=retries,
                pure=False,
            )
            futures[future.key] = (future, job)
        if in_flight is not None:
            in_flight[:] = [job for _, job in futures.values()]
        for future in as_completed([f for f, _ in futures.values()]):
            result = _outcome(future, futures[future.key][1], retries)
            del futures[future.key]  # an interrupt from here on: the caller has the result
            if in_flight is not None:
                in_flight[:] = [j for _, j in futures.values()]
            yield result
        folders = {job.folder for job in jobs}
        for folder in folders:
            remove_temporary_sets(Path(settings.out, folder) if folder else Path(settings.out))
    finally:
        try:
            if futures:  # interrupted (or closed early): see the module notes
                _stop(client, futures, retries, late, left_running)
        finally:
            with contextlib.suppress(Exception):
                client.unsubscribe_topic(topic)
            with contextlib.suppress(Exception):
                client.close()


def _outcome(future, job: ImageJob, retries: int) -> ImageResult:
    """The result of a finished task."""
    from distributed.scheduler import KilledWorker

    try:
        return future.result()
    except KilledWorker as exc:
        return _failed(job, f"workers died while processing it ({exc})", "worker")
    except ImageTaskError as exc:
        return _failed(job, str(exc), "error", retries + 1)
    except Exception as exc:  # noqa: BLE001 - one image's task
        return _failed(job, error_message(job.path, exc), "error", retries + 1)


def _stop(client, futures: dict, retries: int, late: list | None, left: list | None) -> None:
    """Cancel the tasks not started, wait for the running ones, collect what ended."""
    from distributed import wait as dask_wait

    late = [] if late is None else late
    left = [] if left is None else left
    running: set = set()
    try:
        for keys in client.processing().values():
            running.update(keys)
    except Exception:  # noqa: BLE001 - then every unfinished task is waited for
        running = {key for key, (f, _) in futures.items() if not f.done()}
    waiting = [f for key, (f, _) in futures.items() if key not in running and not f.done()]
    with contextlib.suppress(Exception):
        client.cancel(waiting)
    busy = [f for key, (f, _) in futures.items() if key in running and not f.done()]
    if busy:
        log.warning(
            "interrupted: waiting up to %g s for the %d image(s) running on the cluster "
            "(Ctrl-C again to stop waiting)",
            STOP_GRACE,
            len(busy),
        )
        try:
            dask_wait(busy, timeout=STOP_GRACE)
        except KeyboardInterrupt:
            pass
        except Exception:  # noqa: BLE001 - the timeout: what ended is collected below
            pass
    for key, (future, job) in list(futures.items()):
        if future.done() and future.status != "cancelled":
            late.append(_outcome(future, job, retries))
        elif key in running:
            left.append(job)
    with contextlib.suppress(Exception):
        client.cancel([f for f, _ in futures.values() if not f.done()])


def _failed(job: ImageJob, message: str, failure: str, attempts: int = 1) -> ImageResult:
    text = message if job.path in message else f"{job.path}: {message}"
    return ImageResult(
        job.index,
        job.key,
        job.path,
        "failed",
        " ".join(text.split()),
        attempts=attempts,
        failure=failure,
    )
