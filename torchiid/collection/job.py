"""One image of a collection: load it, decompose it, write its output set, say what happened.

:func:`process_image` is what every way of running a collection calls for each image: the
``torchiid decompose`` process itself, each of its ``--workers`` processes, and each Dask
worker. It never raises for a bad input: the :class:`ImageResult` says ``"failed"`` with the
one-line message. Each process keeps what is worth keeping between images (threads, the shared
mask, the loaded feature extractor) in :func:`~.worker.worker_state`, built once per process
and run settings. A process that cannot be set up (the model missing or not loadable, the
device, the ``--mask`` file) raises :class:`~.worker.SetupError` from it: the ``decompose``
process and the ``--workers`` pool stop the run on it; :func:`process_image` (a Dask task)
records it as an ``"error"`` failure, which a rerun tries again, never as a bad input.

Outputs already there: without ``overwrite`` an image whose files exist is refused, unless they
are this very decomposition — every file present and ``-info.json`` recording the same input
SHA-256, parameters hash and SHA-256 of the image's own mask, if any (``"recovered"``: a run
stopped after the files were in place but before the manifest said so, or a worker died just
after its commit; see :func:`~.image_files.recorded`).

``TORCHIID_TEST_HOLD=<stem>:<folder>`` (tests only): the first time an image of that stem has
been written, before its files are put in place, the process writes its pid into
``<folder>/<stem>.pid`` and waits there (up to a minute, or until ``<folder>/<stem>.go``
exists) to be killed or interrupted.
"""

from __future__ import annotations

import logging
import os
import socket
import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from torchiid.baselines.retinex import retinex_decomposition
from torchiid.collection.image_files import output_names, recorded, saved_info, write_outputs
from torchiid.collection.method import run_method
from torchiid.collection.records import ImageJob, ImageResult, InterruptedAfterCommit
from torchiid.collection.settings import (
    RETINEX_DEFAULTS,
    RunSettings,
    file_sha256,
    params_hash,
)
from torchiid.collection.worker import SetupError, worker_state
from torchiid.core.exceptions import (
    ImageError,
    InputWarning,
    MemoryLimitError,
    ModelError,
    TorchiidError,
    caused_by_interrupt,
    describe_error,
    one_line,
)
from torchiid.io import load_image, load_mask
from torchiid.io.decode import declared_size
from torchiid.io.layers import OutputError, OutputSet
from torchiid.model import check_memory, decompose

__all__ = [
    "ImageJob",
    "ImageResult",
    "InterruptedAfterCommit",
    "RETINEX_DEFAULTS",
    "RunSettings",
    "SetupError",
    "error_message",
    "file_sha256",
    "output_names",
    "params_hash",
    "process_image",
    "solver_note",
    "worker_state",
]

log = logging.getLogger("torchiid")


def error_message(path: str | os.PathLike, exc: BaseException) -> str:
    """One line naming the input and the problem."""
    msg = describe_error(exc)
    return msg if str(path) in msg else f"{path}: {msg}"


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _test_hold(stem: str) -> None:
    want = os.environ.get("TORCHIID_TEST_HOLD")
    if not want:
        return
    name, _, folder = want.partition(":")
    marker = Path(folder) / f"{stem}.pid"
    if name != stem or marker.exists():
        return
    tmp = marker.with_suffix(".tmp")
    tmp.write_text(str(os.getpid()))
    os.replace(tmp, marker)
    go = Path(folder) / f"{stem}.go"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not go.exists():
        time.sleep(0.05)


def solver_note(
    where: str, solves: list, converge: bool, info_name: str
) -> tuple[str | None, str | None]:
    """What to say about solves that stopped before their tolerance: ``(note, detail)``.

    With ``converge`` (the ``converged`` preset) a capped solve is a note the user sees: the
    result is not the energy's minimiser. Otherwise the caps are the preset's on purpose (the
    tuned, early-stopped solvers): nothing to warn about, a detail for ``-v``. Either way every
    solve is recorded in ``info_name``.

    Args:
        where: the input, to name in the line.
        solves: the decomposition's :class:`~torchiid.model.SolveReport` list.
        converge: ``params.converge``.
        info_name: the file that records the solves.

    Returns:
        ``(note, None)``, ``(None, detail)`` or ``(None, None)`` when every solve converged.
    """
    capped = [r for r in solves if not r.converged]
    if not capped:
        return None, None
    worst = max(capped, key=lambda r: r.residual / r.tolerance)
    if not converge:
        why = "the preset's caps"
    elif all(r.capped for r in capped):
        why = "safety caps: raise cg_max_iter / bregman_iter"
    else:
        why = (
            "some could make no further progress, which larger caps would not change; "
            "--verbose says which"
        )
    line = (
        f"{where}: {len(capped)} of {len(solves)} solver runs stopped before their tolerance "
        f"({why}; largest residual "
        f"{worst.residual:.1g} against {worst.tolerance:g}); details in {info_name}"
    )
    return (line, None) if converge else (None, line)


def process_image(
    job: ImageJob,
    settings: RunSettings,
    *,
    decompose_fn: Callable[..., Any] = decompose,
    show_progress: bool = False,
    phash: str | None = None,
    release_models: bool = False,
) -> ImageResult:
    """Decompose one image and put its files in place; never raises for a bad input.

    Args:
        job: the image.
        settings: the run's settings.
        decompose_fn: the decomposition (:func:`torchiid.model.decompose` or a function of the
            same signature); unused for ``method="retinex"``.
        show_progress: show an iteration bar (for the ``decompose`` process itself).
        phash: ``params_hash(settings)`` if already computed.
        release_models: give back the CNN's memory once this image's Stage 0 is done
            (:func:`~torchiid.features.patches.release_feature_extractors`), for a process
            with no image left after this one.

    Returns:
        The :class:`ImageResult`: ``"done"`` with the files written (paths relative to the
        output folder), or ``"failed"`` with the one-line message and what failed:
        ``"input"`` (the file, or its own mask, cannot be used: a :class:`TorchiidError`),
        ``"output"`` (an output exists or cannot be written:
        :class:`~torchiid.io.layers.OutputError`) or ``"error"`` (anything unexpected, a
        :class:`~torchiid.core.exceptions.ModelError`, a
        :class:`~torchiid.core.exceptions.MemoryLimitError` or a process that cannot be set
        up).

    Raises:
        KeyboardInterrupt: interrupted; nothing of the image was put in place.
        SetupError: never: a process that cannot be set up makes an ``"error"`` result (see
            :func:`worker_state`; the ``decompose`` process and the pool check it first).
        InterruptedAfterCommit: interrupted while the files were put in place; they are.
    """
    t0 = time.perf_counter()
    params = settings.params
    phash = phash or params_hash(settings)
    stem, folder = job.stem, job.folder
    out_dir = Path(settings.out, folder) if folder else Path(settings.out)
    result = ImageResult(job.index, job.key, job.path, "failed", attempts=job.attempt)
    result.worker = _worker_name()
    names = output_names(stem, settings, params)
    try:
        _identify_input(job, result)
        try:
            state = worker_state(settings)
        except SetupError as exc:  # not the image's fault: an "error", tried again
            result.message = f"{job.path}: not processed: {one_line(str(exc))}"
            result.failure = "error"
            result.seconds = time.perf_counter() - t0
            return result
        tx = OutputSet(out_dir, overwrite=settings.overwrite, label=stem)
        if _found_complete(job, settings, out_dir, names, phash, result):
            result.status, result.recovered = "done", True
            result.files = [f"{folder}/{n}" if folder else n for n in names]
            result.seconds = time.perf_counter() - t0
            return result
        loaded, mask = _load_input(job, settings, state.shared_mask, result)
        batch = loaded.image[None].to(state.device)
        mbatch = mask[None].to(state.device) if mask is not None else None
        if settings.method == "retinex":
            decomposition = retinex_decomposition(batch, params, mask=mbatch, **RETINEX_DEFAULTS)
        else:
            decomposition = run_method(
                decompose_fn,
                batch,
                mbatch,
                settings,
                stem,
                show_progress=show_progress,
                release_models=release_models,
            )
        seconds = time.perf_counter() - t0
        extra = {"input_sha256": result.sha256, "params_hash": phash}
        if job.mask is not None:
            extra["mask"] = str(job.mask)
            extra["mask_sha256"] = result.mask_sha256
        if loaded.mask is not None:
            extra["alpha_mask"] = True  # the file's alpha channel is (part of) the mask
        with tx:
            write_outputs(tx, stem, loaded, decomposition, settings, params, seconds, extra)
            _test_hold(stem)
            try:
                placed = tx.commit()
            except KeyboardInterrupt:
                if not tx.committed:
                    raise
                placed = [out_dir / n for n in tx.names]
                _finish(result, placed, settings, t0, decomposition, stem)
                raise InterruptedAfterCommit(result) from None
        _finish(result, placed, settings, t0, decomposition, stem)
        return result
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - one bad input must not stop the batch
        if caused_by_interrupt(exc):
            # Ctrl-C inside a compiled kernel: numba's dispatcher turns the KeyboardInterrupt
            # into "SystemError: ... returned a result with an exception set" (the interrupt
            # is its cause); it is an interruption, not a failed image
            raise KeyboardInterrupt from exc
        result.status = "failed"
        result.message = error_message(job.path, exc)
        if result.sha256 is None and result.size is not None:
            try:  # the file exists: a rerun skips it while it is unchanged
                result.sha256 = file_sha256(job.path)
            except OSError:
                pass
        result.failure = _failure_kind(exc)
        result.seconds = time.perf_counter() - t0
        if result.retryable:
            log.info("the error below came from here:", exc_info=exc)
        return result


def _identify_input(job: ImageJob, result: ImageResult) -> None:
    """Record the input's size and time, and its own mask's SHA-256, in ``result``."""
    try:
        st = os.stat(job.path)
        result.size, result.mtime_ns = st.st_size, st.st_mtime_ns
    except OSError:
        pass
    if job.mask is not None:  # first: every record of the image names its mask
        try:
            result.mask_sha256 = file_sha256(job.mask)
        except OSError:
            result.mask_sha256 = None  # missing: load_mask says why, below


def _found_complete(
    job: ImageJob,
    settings: RunSettings,
    out_dir: Path,
    names: list[str],
    phash: str,
    result: ImageResult,
) -> bool:
    """Whether the image's files are there and are this decomposition (see the module notes).

    Raises:
        OutputError: a file is there and is not (without ``overwrite``), or a folder stands
            where a file goes.
    """
    for name in names:
        target = out_dir / name
        if target.is_dir() and not target.is_symlink():
            raise OutputError(f"{target}: is a folder; cannot replace it by an output")
        if os.path.lexists(target) and not settings.overwrite:
            try:
                result.sha256 = file_sha256(job.path)
            except OSError:
                result.sha256 = None
            same = result.sha256 and not settings.redo
            if same and recorded(
                out_dir, names, job.stem, result.sha256, phash, result.mask_sha256
            ):
                return True
            why = _why_not_done(out_dir, job, result, phash, settings.redo)
            raise OutputError(f"{target} exists{why}; pass --overwrite to replace it")
    return False


def _why_not_done(out_dir: Path, job: ImageJob, result: ImageResult, phash: str, redo: bool) -> str:
    """Why the files there are not this decomposition, as `` (...)``; empty when unknown."""
    info = saved_info(out_dir, job.stem)
    if redo:
        why = "--redo runs every input again"
    elif info is None or "input_sha256" not in info or result.sha256 is None:
        return ""  # no record of torchiid's, or an input that cannot be read: no comparison
    elif info.get("written_by") == "edit":
        why = "written by torchiid edit, with no record of its parameters"
    elif info.get("input_sha256") != result.sha256:
        why = f"decomposed from another version of {job.path}, or from another file"
    elif info.get("params_hash") != phash:
        why = "written with other parameters"
    elif info.get("mask_sha256") != result.mask_sha256:
        why = "written with another mask"
    else:
        why = "some of the image's files are missing"
    return f" ({why})"


def _load_input(job: ImageJob, settings: RunSettings, shared_mask: Any, result: ImageResult):
    """The loaded image and the mask it is decomposed under (its own, ``--mask``, the file's).

    What the loader changed (a float file's stray negatives set to 0) becomes the image's note.
    The memory check runs on the size the file declares before its pixels are decoded: a
    small file can declare a picture that takes gigabytes once decoded.
    """
    size = declared_size(job.path) if settings.method == "semantic" else None
    if size is not None:
        flags = {"return_stage1": True, "return_iterations": settings.save_iterations}
        check_memory(*size, settings.params, **flags)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # said once, in the image's note
        loaded = load_image(job.path, linear=settings.linear)
    result.note = "\n".join(n for n in (loaded.negatives_note(), _alpha_note(loaded)) if n) or None
    result.sha256 = file_sha256(job.path)
    image, mask = loaded.image, loaded.mask
    masks = [(settings.mask, shared_mask)]
    if job.mask is not None:
        masks.append((job.mask, load_mask(job.mask)))
    for mask_path, m in masks:
        if m is None:
            continue
        if m.shape[-2:] != image.shape[-2:]:
            (mh, mw), (h, w) = m.shape[-2:], image.shape[-2:]
            raise ImageError(f"{job.path}: is {w}x{h} px but the mask {mask_path} is {mw}x{mh} px")
        mask = m if mask is None else (mask & m)
    return loaded, mask


def _alpha_note(loaded: Any) -> str | None:
    """A note when the file's alpha channel leaves pixels out of the decomposition."""
    if loaded.mask is None:
        return None
    total = loaded.mask.numel()
    outside = total - int(loaded.mask.sum())
    if outside == 0:
        return None
    share = f"{outside / total:.1%}" if outside / total >= 0.001 else f"{outside} px"
    return (
        f"{loaded.path}: its alpha channel is the mask: the {share} of its pixels that are at "
        "most half opaque are left out (0 in the layers)"
    )


def _failure_kind(exc: Exception) -> str:
    """``"output"``, ``"input"`` or ``"error"`` (see :func:`process_image`)."""
    if isinstance(exc, OutputError):
        return "output"
    if isinstance(exc, MemoryLimitError):
        # the machine's memory at this moment, not the file: a rerun (or Dask, on a worker
        # that may have more) tries it again
        return "error"
    if isinstance(exc, TorchiidError) and not isinstance(exc, ModelError):
        return "input"
    return "error"


def _finish(result, placed, settings, t0, decomposition, stem) -> None:
    result.status = "done"
    result.files = [Path(os.path.relpath(p, settings.out)).as_posix() for p in placed]
    result.seconds = time.perf_counter() - t0
    note, result.detail = solver_note(
        result.path, list(decomposition.solves), settings.params.converge, f"{stem}-info.json"
    )
    # the loader's note first, then the solvers' (one line each)
    result.note = "\n".join(n for n in (result.note, note) if n) or None


def with_attempt(job: ImageJob, attempt: int) -> ImageJob:
    """The same job, marked as attempt ``attempt``."""
    return replace(job, attempt=attempt)
