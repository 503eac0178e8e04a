"""Evaluation runs: decompose (or read) every image of a dataset, score it, keep the results.

:class:`EvalRunner` (and its shorthand :func:`run_evaluation`) is the library behind
``torchiid eval``: dataset + method + parameters + output folder -> per-image rows and a
summary. The metrics of each dataset are those of :mod:`torchiid.eval.scoring`.

Outputs in the output folder:

- ``results.csv``: a row per image (``id``, the dataset's :data:`METRICS`, ``seconds``),
  appended and flushed as images finish, so an interrupted run resumes where it stopped.
- ``summary.json``: settings, parameters, status, means, median seconds per image and
  failures; for ``saw`` also the AP pooled over every image (``pooled_ap``).
- ``saw-scores/<id>.npz`` (``saw`` only): each image's pixel scores, pooled into that AP.

Resuming: with ``resume=True`` the ids already in ``results.csv`` are skipped and counted in
the summary; the run's settings must match those in ``summary.json``. ``resume=False``
refuses to touch an existing ``results.csv``; ``overwrite=True`` discards it and starts
over. Failed images get no row, so a resumed run retries them.

Batching: images of equal size are decomposed together in batches of ``batch_size`` (at
most ``4 × batch_size`` images wait in memory for a partner of their size); when a batch
fails, its images are run one by one so only the culprit fails.

``seconds``: the method's wall time per image (a batch's time divided by its size; dataset
reading and scoring excluded); when scoring a results folder, the time to read and score.
"""

from __future__ import annotations

import csv
import inspect
import json
import logging
import math
import os
import shutil
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

import torchiid.model
from torchiid._version import __version__
from torchiid.baselines.result import BaselineResult
from torchiid.baselines.retinex import color_retinex
from torchiid.baselines.trivial import reflectance_is_image, shading_is_image
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.eval.datasets import (
    DatasetError,
    DenseFolderDataset,
    DenseSample,
    IIWDataset,
    IIWSample,
    MITDataset,
    SAWDataset,
    SAWSample,
    read_id_list,
)
from torchiid.eval.results import load_layer
from torchiid.eval.scoring import COUNT_COLUMNS, DATASETS, METRICS, pooled_saw_ap, score_sample
from torchiid.params import Parameters

__all__ = [
    "BASELINES",
    "COUNT_COLUMNS",
    "DATASETS",
    "EvalResult",
    "EvalRunner",
    "METHODS",
    "METRICS",
    "SETTINGS",
    "default_output_dir",
    "method_parameters",
    "open_dataset",
    "run_evaluation",
    "run_method",
]

log = logging.getLogger(__name__)

Sample = IIWSample | DenseSample | SAWSample
EvalDataset = IIWDataset | MITDataset | SAWDataset | DenseFolderDataset

METHODS = ("semantic", "retinex", "r=i", "s=i")
"""``semantic``: the paper's method (:func:`torchiid.model.decompose`); the others are
:data:`BASELINES`."""

BASELINES: dict[str, Callable[..., BaselineResult]] = {
    "retinex": color_retinex,
    "r=i": reflectance_is_image,
    "s=i": shading_is_image,
}
"""The baseline methods, each called as ``fn(image, mask=mask)``."""

SETTINGS = ("dataset", "dir", "method", "results_dir", "input", "delta", "parameters")
"""The ``summary.json`` keys a resumed run must match."""


# --------------------------------------------------------------------------- datasets


def open_dataset(
    dataset: str,
    root: str | Path,
    ids: Sequence[str] | str | Path | None = None,
    *,
    input: str = "diffuse",
) -> EvalDataset:
    """Open an evaluation dataset by layout name.

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"`` (see
            :mod:`torchiid.eval.datasets`).
        root: the dataset directory.
        ids: the ids to evaluate, in this order: a sequence, or the path of a file of ids
            (one a line, e.g. an IIW/SAW test split); ``None`` for every image.
        input: MIT input image, ``"diffuse"`` (the standard protocol) or ``"original"``.

    Returns:
        The dataset reader; its ``ids`` are the selected ids.

    Raises:
        DatasetError: missing directory or files, or ids that are not in the dataset.
        ParameterError: unknown ``dataset``.
    """
    if dataset not in DATASETS:
        raise ParameterError(f"unknown dataset {dataset!r}; choose one of {', '.join(DATASETS)}")
    root = Path(root)
    from_file = isinstance(ids, (str, Path))
    wanted = read_id_list(ids) if from_file else None if ids is None else [str(i) for i in ids]
    if dataset == "iiw":
        return IIWDataset(root, ids=wanted)
    if dataset == "mit":
        return MITDataset(root, objects=wanted, input=input)
    if dataset == "saw":
        return SAWDataset(root, ids=wanted)
    ds = DenseFolderDataset(root)
    if wanted is not None:
        missing = sorted(set(wanted) - set(ds.ids))
        if missing:
            which = f"ids of {ids}" if from_file else "of the given ids"
            raise DatasetError(f"{len(missing)} {which} are not in {root}: {missing[:5]}")
        ds.ids = tuple(wanted)
    return ds


def _method_mask(dataset: str, sample: Sample) -> torch.Tensor | None:
    """The mask the method runs under: the object mask (mit, dense), else the whole photo."""
    return sample.mask if dataset in ("mit", "dense") else None


# --------------------------------------------------------------------------- methods


def run_method(
    method: str,
    image: torch.Tensor,
    mask: torch.Tensor | None = None,
    params: Parameters | None = None,
) -> Any:
    """Decompose ``image`` with one of :data:`METHODS`.

    Args:
        method: ``"semantic"`` (:func:`torchiid.model.decompose`), ``"retinex"``,
            ``"r=i"`` or ``"s=i"`` (:data:`BASELINES`).
        image: linear RGB ``(B, 3, H, W)``.
        mask: ``(B, 1, H, W)`` bool pixels to decompose, or ``None`` for all.
        params: parameters of ``semantic`` (default: the ``default`` preset); ignored by
            the baselines.

    Returns:
        An object with ``reflectance`` ``(B, 3, H, W)`` and ``shading`` ``(B, 1, H, W)``,
        linear: a :class:`torchiid.model.Decomposition` or a
        :class:`~torchiid.baselines.BaselineResult`.

    Raises:
        ParameterError: unknown ``method``.
        TorchiidError: the method failed on this input.
    """
    if method in BASELINES:
        return BASELINES[method](image, mask=mask)
    if method != "semantic":
        raise ParameterError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    return torchiid.model.decompose(image, params, mask=mask)


def method_parameters(method: str, params: Parameters | None = None) -> dict[str, Any]:
    """The parameters a method runs with, as recorded in ``summary.json``.

    Args:
        method: one of :data:`METHODS` (anything else has no parameters).
        params: parameters of ``semantic`` (default: the ``default`` preset).

    Returns:
        ``semantic``: ``params.to_dict()``; ``retinex``: the defaults of
        :func:`~torchiid.baselines.color_retinex`; otherwise ``{}``.
    """
    if method == "semantic":
        return (params if params is not None else Parameters.preset("default")).to_dict()
    if method == "retinex":
        sig = inspect.signature(color_retinex).parameters.values()
        return {
            p.name: p.default
            for p in sig
            if p.default is not inspect.Parameter.empty and p.name != "mask"
        }
    return {}


def default_output_dir(dataset: str, method: str) -> Path:
    """``eval-<dataset>-<method>`` in the working directory (``method`` may be ``results``)."""
    return Path(f"eval-{dataset}-{method}")


# --------------------------------------------------------------------------- files


def _fmt(column: str, v: float) -> str:
    return str(int(v)) if column in COUNT_COLUMNS else repr(float(v))


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False, allow_nan=False) + "\n")
    os.replace(tmp, path)


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _read_rows(path: Path, columns: list[str]) -> dict[str, dict[str, float]]:
    """Complete rows of an existing ``results.csv`` (a torn last line is dropped)."""
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            return {}
        if header != columns:
            raise TorchiidError(
                f"{path} has columns {header}, expected {columns}; use another -o or --overwrite"
            )
        rows = {}
        for rec in reader:
            if len(rec) != len(columns):
                continue
            try:
                rows[rec[0]] = {c: float(v) for c, v in zip(columns[1:], rec[1:], strict=True)}
            except ValueError:
                continue
    return rows


def _prepare_output(
    out: Path, settings: dict[str, Any], columns: list[str], *, resume: bool, overwrite: bool
) -> dict[str, dict[str, float]]:
    """Create / check the output folder; return the rows already done (when resuming)."""
    if out.exists() and not out.is_dir():
        raise TorchiidError(f"{out}: output exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    csv_path, summary_path = out / "results.csv", out / "summary.json"
    if overwrite:
        for p in (csv_path, summary_path):
            p.unlink(missing_ok=True)
        shutil.rmtree(out / "saw-scores", ignore_errors=True)
    elif csv_path.exists() and not resume:
        raise TorchiidError(
            f"{csv_path} exists; pass --resume to continue that run or --overwrite to discard it"
        )
    done: dict[str, dict[str, float]] = {}
    if csv_path.exists():
        if summary_path.is_file():
            try:
                old = json.loads(summary_path.read_text())
            except (OSError, ValueError) as exc:
                raise TorchiidError(f"cannot read {summary_path}: {exc}") from exc
            differ = [k for k in SETTINGS if old.get(k) != settings[k]]
            if differ:
                raise TorchiidError(
                    f"{out} holds a run with other settings ({', '.join(differ)}"
                    "); use another -o or --overwrite"
                )
        done = _read_rows(csv_path, columns)
    tmp = out / ".results.csv.tmp"
    with tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for i, row in done.items():
            writer.writerow([i, *(_fmt(c, row[c]) for c in columns[1:])])
    os.replace(tmp, csv_path)
    return done


def _guard(sample_id: str, fn: Callable[[], Any], fail: Callable[[str, Exception], None]) -> Any:
    """Call ``fn``; a :class:`TorchiidError` is recorded against the image and gives ``None``."""
    try:
        return fn()
    except TorchiidError as exc:
        fail(sample_id, exc)
        return None


def _log_failure(sample_id: str, exc: Exception) -> None:
    log.warning("%s: %s", sample_id, exc)


# --------------------------------------------------------------------------- runner


@dataclass(frozen=True, eq=False)
class EvalResult:
    """The outcome of :meth:`EvalRunner.run`.

    Attributes:
        ids: every id of the run (after ``ids`` and ``limit``), in order.
        columns: the ``results.csv`` header: ``id``, the dataset's metrics, ``seconds``.
        rows: ``{id: {column: value}}`` of the scored ids of this run (including those of
            earlier, resumed runs), in the order of ``ids``.
        failures: ``{id: error message}`` of the images that failed in this run.
        summary: what ``summary.json`` holds (settings, ``status``, ``n_images``,
            ``n_scored``, ``mean``, ``median_seconds``, ``failures``; for ``saw`` also
            ``pooled_ap`` and ``pooled_ap_images``).
        output: the output folder.
    """

    ids: tuple[str, ...]
    columns: tuple[str, ...]
    rows: dict[str, dict[str, float]]
    failures: dict[str, str]
    summary: dict[str, Any]
    output: Path

    @property
    def csv_path(self) -> Path:
        """``<output>/results.csv``."""
        return self.output / "results.csv"

    @property
    def summary_path(self) -> Path:
        """``<output>/summary.json``."""
        return self.output / "summary.json"

    @property
    def ok(self) -> bool:
        """Every image of the run was scored (no failures)."""
        return not self.failures


class EvalRunner:
    """Score a method (or a folder of decompositions) on an evaluation dataset.

    Construction checks the arguments and resolves the device; :meth:`run` does the work
    (see the module docstring for the output files, resuming and batching).

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"``.
        root: the dataset directory.
        method: one of :data:`METHODS`; ignored when ``results_dir`` is given.
        params: parameters of ``semantic`` (default: the ``default`` preset).
        output: output folder (default: :func:`default_output_dir`, in the working
            directory).
        results_dir: score the layers in this folder (read with
            :func:`~torchiid.eval.results.load_layer`) instead of running ``method``; the
            run's method is then ``"results"``.
        device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"`` or a
            :class:`torch.device`.
        batch_size: images of equal size decomposed together.
        limit: evaluate only the first ``limit`` images of the set.
        ids: ids to evaluate (a sequence or an id-list file), see :func:`open_dataset`.
        input: MIT input image, ``"diffuse"`` or ``"original"``.
        delta: WHDR equality margin (``iiw``).
        resume: skip the ids already in ``results.csv``; if ``False``, an existing
            ``results.csv`` is an error.
        overwrite: discard existing results in the output folder and start over.
        progress: show a progress bar on stderr.
        on_failure: called with ``(id, exception)`` when an image fails (default: a
            warning on the ``torchiid.eval.runner`` logger).

    Raises:
        ParameterError: unknown dataset or method, ``batch_size < 1``, ``limit < 1``, or
            ``delta`` negative or NaN.
        TorchiidError: ``results_dir`` is not a directory, or CUDA was asked for and is
            unavailable.

    Example:
        A run from Python (the dataset folder is the MIT-Berkeley release)::

            runner = EvalRunner("mit", "mit-berkeley", method="r=i", output="eval-mit")
            result = runner.run()
            print(result.summary["mean"]["lmse"], result.failures)
    """

    def __init__(
        self,
        dataset: str,
        root: str | Path,
        *,
        method: str = "semantic",
        params: Parameters | None = None,
        output: str | Path | None = None,
        results_dir: str | Path | None = None,
        device: str | torch.device = "auto",
        batch_size: int = 1,
        limit: int | None = None,
        ids: Sequence[str] | str | Path | None = None,
        input: str = "diffuse",
        delta: float = 0.10,
        resume: bool = True,
        overwrite: bool = False,
        progress: bool = False,
        on_failure: Callable[[str, Exception], None] | None = None,
    ) -> None:
        if dataset not in DATASETS:
            raise ParameterError(
                f"unknown dataset {dataset!r}; choose one of {', '.join(DATASETS)}"
            )
        if method not in METHODS:
            raise ParameterError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        if batch_size < 1:
            raise ParameterError(f"batch_size must be >= 1, got {batch_size}")
        if limit is not None and limit < 1:
            raise ParameterError(f"limit must be >= 1, got {limit}")
        if not delta >= 0:
            raise ParameterError(f"delta must be >= 0, got {delta}")
        self.results_dir = None if results_dir is None else Path(results_dir)
        if self.results_dir is not None and not self.results_dir.is_dir():
            raise TorchiidError(f"results directory {self.results_dir} does not exist")
        self.dataset = dataset
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise TorchiidError(f"{self.root}: is a file, not a {dataset} dataset directory")
        self.method = "results" if self.results_dir is not None else method
        self.params = params
        self.output = (
            Path(output) if output is not None else default_output_dir(dataset, self.method)
        )
        self.device = device if isinstance(device, torch.device) else resolve_device(device)
        self.batch_size = batch_size
        self.limit = limit
        self.ids = ids
        self.input = input
        self.delta = delta
        self.resume = resume
        self.overwrite = overwrite
        self.progress = progress
        self.on_failure = on_failure if on_failure is not None else _log_failure

    def settings(self) -> dict[str, Any]:
        """The run's settings as ``summary.json`` records them (a resumed run must match)."""
        scoring = self.results_dir is not None
        settings = {
            "dataset": self.dataset,
            "dir": str(self.root.resolve()),
            "method": self.method,
            "results_dir": str(self.results_dir.resolve()) if scoring else None,
            "input": self.input if self.dataset == "mit" else None,
            "delta": self.delta if self.dataset == "iiw" else None,
            "parameters": {} if scoring else method_parameters(self.method, self.params),
        }
        return json.loads(json.dumps(settings))  # as summary.json will hold them

    def run(self) -> EvalResult:
        """Evaluate every selected image and write the output folder.

        Images that fail (unreadable files, a method error, missing result layers: any
        :class:`TorchiidError`) are reported to ``on_failure`` and listed in the summary;
        the others are scored. ``summary.json`` is rewritten at the end, also when the run
        is interrupted (``status`` ``"stopped"``).

        Returns:
            The rows and the summary.

        Raises:
            DatasetError: the dataset cannot be opened.
            TorchiidError: the output folder holds an incompatible run (other settings or
                columns, or ``resume=False`` with an existing ``results.csv``).
        """
        reader = open_dataset(self.dataset, self.root, self.ids, input=self.input)
        ids = list(reader.ids)[: self.limit]
        columns = ["id", *METRICS[self.dataset], "seconds"]
        settings = self.settings()
        out = self.output
        done = _prepare_output(out, settings, columns, resume=self.resume, overwrite=self.overwrite)
        return _Run(self, reader, ids, columns, settings, done).execute()


class _Run:
    """The state of one :meth:`EvalRunner.run` (rows, failures, open CSV, progress bar)."""

    def __init__(
        self,
        runner: EvalRunner,
        reader: EvalDataset,
        ids: list[str],
        columns: list[str],
        settings: dict[str, Any],
        done: dict[str, dict[str, float]],
    ) -> None:
        self.runner = runner
        self.reader = reader
        self.ids = ids
        self.columns = columns
        self.settings = settings
        self.out = runner.output
        self.rows = {i: done[i] for i in ids if i in done}
        self.failures: dict[str, str] = {}
        self.started = time.strftime("%Y-%m-%dT%H:%M:%S")
        self.csv_file: Any = None
        self.writer: Any = None
        self.bar: Any = None

    def summary(self, status: str) -> dict[str, Any]:
        ids, rows = self.ids, self.rows
        scored = [i for i in ids if i in rows]
        means = {}
        for c in self.columns[1:-1]:
            vals = [rows[i][c] for i in scored if math.isfinite(rows[i][c])]
            means[c] = _finite_or_none(statistics.fmean(vals)) if vals else None
        data = {
            "torchiid_version": __version__,
            **self.settings,
            "status": status,
            "started": self.started,
            "device": str(self.runner.device),
            "n_images": len(ids),
            "n_scored": len(scored),
            "mean": means,
        }
        if self.runner.dataset == "saw":
            ap, n = pooled_saw_ap(self.out / "saw-scores", scored)
            data["pooled_ap"], data["pooled_ap_images"] = _finite_or_none(ap), n
        times = [rows[i]["seconds"] for i in scored]
        data["median_seconds"] = statistics.median(times) if times else None
        data["failures"] = [{"id": i, "error": m} for i, m in self.failures.items()]
        return data

    def record(
        self, sample: Sample, refl: torch.Tensor, shading: torch.Tensor, seconds: float
    ) -> None:
        row = score_sample(
            self.runner.dataset,
            sample,
            refl.detach().cpu().float(),
            shading.detach().cpu().float(),
            delta=self.runner.delta,
            saw_scores_dir=self.out / "saw-scores",
        )
        row["seconds"] = seconds
        self.writer.writerow([sample.id, *(_fmt(c, row[c]) for c in self.columns[1:])])
        self.csv_file.flush()
        self.rows[sample.id] = row

    def fail(self, sample_id: str, exc: Exception) -> None:
        self.failures[sample_id] = str(exc)
        self.runner.on_failure(sample_id, exc)

    def run_batch(self, samples: list[Sample]) -> None:
        device = self.runner.device
        image = torch.stack([s.image for s in samples]).to(device)
        masks = [_method_mask(self.runner.dataset, s) for s in samples]
        mask = None if masks[0] is None else torch.stack(masks).to(device)
        t0 = time.perf_counter()
        try:
            layers = run_method(self.runner.method, image, mask, self.runner.params)
            refl, shading = layers.reflectance, layers.shading
        except TorchiidError as exc:
            if len(samples) > 1:  # find the culprit: run them one by one
                for s in samples:
                    self.run_batch([s])
                return
            self.fail(samples[0].id, exc)
            self.bar.update(1)
            return
        seconds = (time.perf_counter() - t0) / len(samples)
        for k, s in enumerate(samples):
            _guard(
                s.id,
                lambda s=s, k=k: self.record(s, refl[k : k + 1], shading[k : k + 1], seconds),
                self.fail,
            )
            self.bar.update(1)

    def score_results(self, sample: Sample) -> None:
        t0 = time.perf_counter()
        refl = load_layer(self.runner.results_dir, sample.id, "reflectance")
        shading = load_layer(self.runner.results_dir, sample.id, "shading")
        self.record(sample, refl, shading, time.perf_counter() - t0)

    def loop(self) -> None:
        batch_size = self.runner.batch_size
        pending: dict[tuple[int, int], list[Sample]] = {}
        for sample_id in self.ids:
            if sample_id in self.rows:
                continue
            sample = _guard(sample_id, lambda i=sample_id: self.reader.load(i), self.fail)
            if sample is None:
                self.bar.update(1)
                continue
            if self.runner.results_dir is not None:
                _guard(sample_id, lambda s=sample: self.score_results(s), self.fail)
                self.bar.update(1)
                continue
            group = pending.setdefault(tuple(sample.image.shape[-2:]), [])
            group.append(sample)
            if len(group) == batch_size:
                self.run_batch(pending.pop(tuple(sample.image.shape[-2:])))
            elif sum(len(g) for g in pending.values()) >= 4 * batch_size:
                self.run_batch(pending.pop(max(pending, key=lambda k: len(pending[k]))))
        for key in list(pending):
            self.run_batch(pending.pop(key))

    def execute(self) -> EvalResult:
        _write_json(self.out / "summary.json", self.summary("running"))
        self.bar = tqdm(
            total=len(self.ids),
            initial=len(self.rows),
            desc=f"eval {self.runner.dataset}",
            unit="img",
            disable=not self.runner.progress,
            file=sys.stderr,
            leave=False,
        )
        self.csv_file = (self.out / "results.csv").open("a", newline="")
        self.writer = csv.writer(self.csv_file)
        status = "stopped"
        try:
            self.loop()
            status = "complete"
        finally:
            self.csv_file.close()
            self.bar.close()
            data = self.summary(status)
            _write_json(self.out / "summary.json", data)
        return EvalResult(
            ids=tuple(self.ids),
            columns=tuple(self.columns),
            rows={i: self.rows[i] for i in self.ids if i in self.rows},
            failures=dict(self.failures),
            summary=data,
            output=self.out,
        )


def run_evaluation(dataset: str, root: str | Path, **options: Any) -> EvalResult:
    """Shorthand for ``EvalRunner(dataset, root, **options).run()``.

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"``.
        root: the dataset directory.
        **options: the keyword arguments of :class:`EvalRunner` (``method``, ``params``,
            ``output``, ``results_dir``, ``device``, ``batch_size``, ...).

    Returns:
        The rows and the summary (see :class:`EvalResult`).
    """
    return EvalRunner(dataset, root, **options).run()
