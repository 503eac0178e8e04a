"""One image of a collection: load it, decompose it, write its output set, say what happened.

:func:`process_image` is what every way of running a collection calls for each image: the
``torchiid decompose`` process itself, each of its ``--workers`` processes, and each Dask
worker. It never raises for a bad input: the :class:`ImageResult` says ``"failed"`` with the
one-line message. Each process keeps what is worth keeping between images (threads, the shared
mask, the loaded feature extractor) in :func:`worker_state`, built once per process and run
settings. A process that cannot be set up (the model missing or not loadable, the device, the
``--mask`` file) raises :class:`SetupError` from :func:`worker_state`: the ``decompose`` process
and the ``--workers`` pool stop the run on it; :func:`process_image` (a Dask task) records it as
an ``"error"`` failure, which a rerun tries again, never as a bad input.

Outputs already there: without ``overwrite`` an image whose files exist is refused, unless they
are this very decomposition — every file present and ``-info.json`` recording the same input
SHA-256, parameters hash and SHA-256 of the image's own mask, if any (``"recovered"``: a run
stopped after the files were in place but before the manifest said so, or a worker died just
after its commit).

``TORCHIID_TEST_HOLD=<stem>:<folder>`` (tests only): the first time an image of that stem has
been written, before its files are put in place, the process writes its pid into
``<folder>/<stem>.pid`` and waits there (up to a minute, or until ``<folder>/<stem>.go``
exists) to be killed or interrupted.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import socket
import sys
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from torchiid._version import __version__
from torchiid.baselines.retinex import retinex_decomposition
from torchiid.core.exceptions import (
    ConvergenceWarning,
    ImageError,
    MemoryLimitError,
    ModelError,
    TorchiidError,
    caused_by_interrupt,
    describe_error,
    one_line,
)
from torchiid.core.stats import image_quantile
from torchiid.io import load_image, load_mask, save_image
from torchiid.io.layers import ExtraOutputs, OutputError, OutputSet, layer_file_names, write_layers
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.priors.shading_terms import pixel_confidence

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

RETINEX_DEFAULTS = {"threshold_gray": 0.075, "threshold_color": 1.0}

#: bytes read at a time when hashing an input
HASH_CHUNK = 1 << 20


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass(frozen=True)
class RunSettings:
    """Everything about a run that is the same for every image (picklable, sent to workers).

    Attributes:
        out: the output folder (an absolute path when workers on other machines use it).
        params: the method's parameters.
        method: ``"semantic"`` or ``"retinex"``.
        linear: 8/16-bit files hold linear values.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (resolved in each worker).
        overwrite: replace existing output files.
        save_npy, save_confidence, save_stage1, save_iterations: the optional files
            (``save_stage1``: Stage 1's ``-rho.exr``; its ``-sigma.exr`` is always written by
            the semantic method, for ``torchiid edit --from``).
        mask: a mask file for every image, or ``None``.
        mask_sha256: its SHA-256 (part of :attr:`params_hash`).
        threads: torch threads in each worker process (``None``: leave them as they are).
        redo: compute every image again, even where its complete files are there already.
    """

    out: Path
    params: Parameters
    method: str = "semantic"
    linear: bool = False
    device: str = "auto"
    overwrite: bool = False
    save_npy: bool = False
    save_confidence: bool = False
    save_stage1: bool = False
    save_iterations: bool = False
    mask: Path | None = None
    mask_sha256: str | None = None
    threads: int | None = None
    redo: bool = False

    @property
    def params_hash(self) -> str:
        """:func:`params_hash` of these settings."""
        return params_hash(self)


def params_hash(settings: RunSettings) -> str:
    """SHA-256 of what makes an image's files: the parameters and the options that change them.

    The canonical JSON (sorted keys, no spaces) of the full parameter set, the method, whether
    8/16-bit files are linear, the optional files asked for and the SHA-256 of the ``--mask``
    file. Not in it: the torchiid version (a rerun after an upgrade skips what is done;
    ``redo`` makes it again); the device, ``overwrite``, ``redo``, threads and workers, which
    change where and how fast the files are made, not which (the solvers' float sums may
    differ in the last digits between devices and thread counts).
    """
    what = {
        # the parameters alone, not the version that wrote them: a new version that computes
        # the same files keeps the collection's hashes
        "params": settings.params.to_dict(),
        "method": settings.method,
        "linear": settings.linear,
        "save_npy": settings.save_npy,
        "save_confidence": settings.save_confidence,
        "save_stage1": settings.save_stage1 and settings.method == "semantic",
        "save_iterations": settings.save_iterations and settings.method == "semantic",
        "mask_sha256": settings.mask_sha256,
    }
    text = json.dumps(what, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class ImageJob:
    """One image to process: where it is, where its outputs go, which attempt this is."""

    index: int
    path: str
    key: str
    mask: str | None = None
    attempt: int = 1

    @property
    def stem(self) -> str:
        """The prefix of the image's output file names."""
        return self.key.rpartition("/")[2]

    @property
    def folder(self) -> str:
        """The output subfolder (``""``: the output folder itself)."""
        return self.key.rpartition("/")[0]


@dataclass
class ImageResult:
    """What became of one image (one line of the manifest, see :mod:`.manifest`)."""

    index: int
    key: str
    path: str
    status: str  # "done" or "failed"
    message: str | None = None
    files: list[str] = field(default_factory=list)
    seconds: float = 0.0
    sha256: str | None = None
    size: int | None = None
    mtime_ns: int | None = None
    mask_sha256: str | None = None
    attempts: int = 1
    worker: str = ""
    recovered: bool = False
    note: str | None = None  # shown unless -q
    detail: str | None = None  # shown with -v
    failure: str | None = None  # "input", "output", "error" or "worker" (see process_image)

    @property
    def retryable(self) -> bool:
        """A failure that is not the input's nor the output folder's (Dask retries it)."""
        return self.failure == "error"

    @property
    def ok(self) -> bool:
        """The image's files are complete."""
        return self.status == "done"


class InterruptedAfterCommit(KeyboardInterrupt):  # noqa: N818 - it is an interrupt
    """An interrupt that arrived while the image's files were put in place: they are complete.

    Attributes:
        result: the image's (done) result, to be recorded before the run stops.
    """

    def __init__(self, result: ImageResult) -> None:
        super().__init__("interrupted after the files were put in place")
        self.result = result


def output_names(stem: str, settings: Any, params: Parameters) -> list[str]:
    """Every file name ``decompose`` writes for an image of this stem.

    ``settings`` is a :class:`RunSettings` or the command's ``argparse.Namespace`` (the same
    attribute names).
    """
    names = layer_file_names(
        stem, save_npy=settings.save_npy, save_confidence=settings.save_confidence
    )
    if settings.method == "semantic":  # σ always: every `torchiid edit --from` needs it
        names.append(f"{stem}-sigma.exr")
        if getattr(settings, "save_stage1", False):
            names.append(f"{stem}-rho.exr")
    if settings.save_iterations and settings.method == "semantic":
        for k in range(1, params.iterations + 1):
            names += [f"{stem}-iter{k}-{layer}.png" for layer in ("sigma", "rho", "R", "S")]
    return names


def error_message(path: str | os.PathLike, exc: BaseException) -> str:
    """One line naming the input and the problem."""
    msg = describe_error(exc)
    return msg if str(path) in msg else f"{path}: {msg}"


class SetupError(TorchiidError):
    """A process cannot be set up for the run: the model, the device or the ``--mask`` file.

    Not a fault of any image: the run stops (``decompose``, ``--workers``), or the image is
    recorded as an ``"error"`` failure that a rerun tries again (Dask).
    """


@dataclass
class WorkerState:
    """What a process keeps between the images of a run (see :func:`worker_state`)."""

    device: Any
    shared_mask: Any
    threads: int


_STATES: dict[tuple, WorkerState] = {}
_STATES_LOCK = threading.Lock()


def worker_state(settings: RunSettings) -> WorkerState:
    """This process's state for ``settings``, built on its first image and kept.

    Sets the torch threads (``settings.threads``), resolves the device, loads the ``--mask``
    file and, for the semantic method, loads the feature extractor (the ONNX session) once.

    Raises:
        SetupError: any of these failed (one line; the cause chained).
    """
    key = (
        settings.method,
        settings.device,
        str(settings.mask),
        settings.mask_sha256,
        settings.threads,
    )
    with _STATES_LOCK:  # a Dask worker may run several tasks at once
        state = _STATES.get(key)
        if state is None:
            try:
                state = _new_state(settings)
            except Exception as exc:  # noqa: BLE001 - whatever it is, no image can run
                raise SetupError(f"cannot set up the run: {describe_error(exc)}") from exc
            _STATES[key] = state
    return state


def _new_state(settings: RunSettings) -> WorkerState:
    import torch

    from torchiid.core.device import resolve_device
    from torchiid.core.memory import undo_malloc_trim_threshold

    undo_malloc_trim_threshold()  # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ (2-4x slower)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    device = resolve_device(settings.device)
    shared = load_mask(settings.mask) if settings.mask is not None else None
    if settings.method == "semantic":
        from torchiid.features.onnx_backend import OnnxFeatureExtractor

        OnnxFeatureExtractor(device=device.type)  # the session is cached for the process
    return WorkerState(device, shared, torch.get_num_threads())


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


def _recorded(
    out_dir: Path, names: list[str], stem: str, sha: str, phash: str, mask_sha: str | None
) -> bool:
    """The outputs there are complete and record this input, its own mask and these parameters."""
    if not all(os.path.isfile(out_dir / n) for n in names):
        return False
    try:
        info = json.loads((out_dir / f"{stem}-info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (
        isinstance(info, dict)
        and info.get("input_sha256") == sha
        and info.get("params_hash") == phash
        and info.get("mask_sha256") == mask_sha
    )


def _write_outputs(
    tx: OutputSet,
    stem: str,
    loaded: Any,
    result: Any,
    settings: RunSettings,
    params: Parameters,
    seconds: float,
    extra: dict,
) -> None:
    """Write every layer of one image into the output set ``tx`` (:mod:`torchiid.io.layers`)."""
    image = loaded.image
    mask = None if result.mask is None else result.mask[0].cpu()
    confidence = None
    if settings.save_confidence:
        sh = params.shading
        confidence = pixel_confidence(image[None], sh.dark_level, sh.clip_level)[0]
        if mask is not None:
            confidence = confidence * mask
    if settings.method == "semantic":
        params_json = params.to_json()
    else:
        retinex = {"torchiid_version": __version__, "method": "color_retinex", **RETINEX_DEFAULTS}
        params_json = json.dumps(retinex, indent=2) + "\n"
    white = float(result.shading_white[0])
    sigma = settings.method == "semantic" and result.sigma is not None
    rho = sigma and settings.save_stage1
    iterations = settings.save_iterations and getattr(result, "iterations", None)
    info = {
        "input": str(loaded.path),
        "method": settings.method,
        "working_size": list(reversed(result.working_size)) if result.working_size else None,
        "exif_orientation": getattr(loaded, "orientation", 1),
        "albedo_quantile": params.output.albedo_quantile,
        "albedo_excess": float(result.albedo_excess[0]),
        "seconds": round(seconds, 3),
        "converged": result.converged,
        "solves": [str(r) for r in result.solves],
        **extra,
        "files": {},
    }
    if sigma:
        info["files"][f"{stem}-sigma.exr"] = (
            "last Stage 1 shading sigma, float32 linear OpenEXR (rho = I / sigma)"
        )
    if rho:
        info["files"][f"{stem}-rho.exr"] = "last Stage 1 reflectance rho, float32 linear OpenEXR"
    if iterations:
        for k in range(1, len(result.iterations) + 1):
            for name in ("sigma", "rho", "R", "S"):
                info["files"][f"{stem}-iter{k}-{name}.png"] = (
                    f"alternation {k}'s {name} at the working resolution, 8-bit sRGB"
                )
    write_layers(
        tx.out,
        stem,
        image,
        result.reflectance[0].cpu(),
        result.shading[0].cpu(),
        shading_white=white,
        info=info,
        params_json=params_json,
        mask=mask,
        extras=ExtraOutputs(npy=settings.save_npy, confidence=confidence),
        output_set=tx,
    )
    if sigma:
        # the last Stage 1 shading, exact, for `torchiid edit --from` (merge, illumination);
        # its reflectance is the photo divided by it, rebuilt there unless written here
        sg = result.sigma[0].cpu()
        tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sg, "exr"))
    if rho:
        rh = result.rho[0].cpu()
        tx.write(f"{stem}-rho.exr", lambda p: save_image(p, rh, "exr"))
    if iterations:
        named = {"sigma": "sigma", "rho": "rho", "R": "reflectance", "S": "shading"}
        for k, layers in enumerate(result.iterations, start=1):
            for name, attr in named.items():
                x = getattr(layers, attr)[0].cpu()
                if name in ("sigma", "S"):
                    x = x / image_quantile(x[None], params.output.view_quantile).clamp_min(1e-12)[0]
                tx.write(f"{stem}-iter{k}-{name}.png", lambda p, x=x: save_image(p, x, "srgb8"))


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
) -> ImageResult:
    """Decompose one image and put its files in place; never raises for a bad input.

    Args:
        job: the image.
        settings: the run's settings.
        decompose_fn: the decomposition (:func:`torchiid.model.decompose` or a function of the
            same signature); unused for ``method="retinex"``.
        show_progress: show an iteration bar (for the ``decompose`` process itself).
        phash: ``params_hash(settings)`` if already computed.

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
    tx: OutputSet | None = None
    try:
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
        try:
            state = worker_state(settings)
        except SetupError as exc:  # not the image's fault: an "error", tried again
            result.message = f"{job.path}: not processed: {one_line(str(exc))}"
            result.failure = "error"
            result.seconds = time.perf_counter() - t0
            return result
        tx = OutputSet(out_dir, overwrite=settings.overwrite, label=stem)
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
                recorded = same and _recorded(
                    out_dir, names, stem, result.sha256, phash, result.mask_sha256
                )
                if recorded:
                    result.status, result.recovered = "done", True
                    result.files = [f"{folder}/{n}" if folder else n for n in names]
                    result.seconds = time.perf_counter() - t0
                    return result
                raise OutputError(f"{target} exists; pass --overwrite to replace it")
        loaded = load_image(job.path, linear=settings.linear)
        result.sha256 = file_sha256(job.path)
        image, mask = loaded.image, loaded.mask
        masks = [(settings.mask, state.shared_mask)]
        if job.mask is not None:
            masks.append((job.mask, load_mask(job.mask)))
        for mask_path, m in masks:
            if m is None:
                continue
            if m.shape[-2:] != image.shape[-2:]:
                (mh, mw), (h, w) = m.shape[-2:], image.shape[-2:]
                raise ImageError(
                    f"{job.path}: is {w}x{h} px but the mask {mask_path} is {mw}x{mh} px"
                )
            mask = m if mask is None else (mask & m)
        batch = image[None].to(state.device)
        mbatch = mask[None].to(state.device) if mask is not None else None
        if settings.method == "retinex":
            decomposition = retinex_decomposition(batch, params, mask=mbatch, **RETINEX_DEFAULTS)
        else:
            decomposition = _run_method(
                decompose_fn, batch, mbatch, settings, params, stem, show_progress
            )
        seconds = time.perf_counter() - t0
        extra = {"input_sha256": result.sha256, "params_hash": phash}
        if job.mask is not None:
            extra["mask"] = str(job.mask)
            extra["mask_sha256"] = result.mask_sha256
        with tx:
            _write_outputs(tx, stem, loaded, decomposition, settings, params, seconds, extra)
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
        if isinstance(exc, OutputError):
            result.failure = "output"
        elif isinstance(exc, MemoryLimitError):
            # the machine's memory at this moment, not the file: a rerun (or Dask, on a worker
            # that may have more) tries it again
            result.failure = "error"
        elif isinstance(exc, TorchiidError) and not isinstance(exc, ModelError):
            result.failure = "input"
        else:
            result.failure = "error"
        result.seconds = time.perf_counter() - t0
        if result.retryable:
            log.info("the error below came from here:", exc_info=exc)
        return result


def _finish(result, placed, settings, t0, decomposition, stem) -> None:
    result.status = "done"
    result.files = [Path(os.path.relpath(p, settings.out)).as_posix() for p in placed]
    result.seconds = time.perf_counter() - t0
    result.note, result.detail = solver_note(
        result.path, list(decomposition.solves), settings.params.converge, f"{stem}-info.json"
    )


def _run_method(decompose_fn, batch, mbatch, settings, params, stem, show_progress):
    from tqdm import tqdm

    it_bar = tqdm(
        total=params.iterations,
        desc=f"{stem}",
        unit="it",
        disable=not show_progress,
        file=sys.stderr,
        leave=False,
    )

    def progress(stage: str, k: int, total: int, _bar=it_bar) -> None:
        if stage == "iteration":
            _bar.update(1)

    try:
        with warnings.catch_warnings():
            # a solve that hit its cap is reported in the image's one-line note and info.json
            warnings.simplefilter("ignore", ConvergenceWarning)
            return decompose_fn(
                batch,
                params,
                mask=mbatch,
                return_iterations=settings.save_iterations,
                return_stage1=True,  # sigma.exr
                progress=progress,
            )
    finally:
        it_bar.close()


def with_attempt(job: ImageJob, attempt: int) -> ImageJob:
    """The same job, marked as attempt ``attempt``."""
    return replace(job, attempt=attempt)
