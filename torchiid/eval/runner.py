"""Evaluation runs: decompose (or read) every image of a dataset, score it, keep the results.

:class:`EvalRunner` (and its shorthand :func:`run_evaluation`) is the library behind
``torchiid eval``: dataset + method + :class:`EvalOptions` -> per-image rows and a summary.
The metrics of each dataset are those of :mod:`torchiid.eval.scoring`, the methods those of
:mod:`torchiid.eval.methods`.

Outputs in the output folder (:mod:`torchiid.eval.outputs`):

- ``results.csv``: a row per image (``id``, the dataset's :data:`METRICS`, ``seconds``),
  appended and flushed as images finish, so an interrupted run resumes where it stopped.
- ``summary.json``: settings, parameters, status, means, median seconds per image and
  failures; for ``saw`` also the AP pooled over every image (``pooled_ap``).
- ``saw-scores/<id>.npz`` (``saw`` only): each image's pixel scores, pooled into that AP.

Resuming: with ``resume=True`` the ids already in ``results.csv`` are skipped and counted in
the summary; the run's settings must match those in ``summary.json``, and its selection
(``ids``, ``limit``) must include every id of ``results.csv`` (a run may go on to more
images, not to others or fewer), so ``results.csv`` and ``summary.json`` always describe the
same images. ``resume=False`` refuses to touch an existing ``results.csv``;
``overwrite=True`` discards it and starts over. Failed images get no row, so a resumed run
retries them.

Results folders: the layers of each id are read with
:func:`~torchiid.eval.results.load_layer`; a folder that holds no layer file of any id is
refused before any work, and a layer of another size than the image fails that image,
naming the file. Layers that multiply to the input decoded the wrong way (a 16-bit linear
MIT image decomposed as sRGB, :func:`~torchiid.eval.results.input_decoding`) are scored
as they are and named in :attr:`EvalResult.notes`.

Batching: images of equal size are decomposed together in batches of ``batch_size`` (at
most ``4 × batch_size`` images wait in memory for a partner of their size); when a batch
fails, its images are run one by one so only the culprit fails.

``seconds``: the method's wall time per image (a batch's time divided by its size; dataset
reading and scoring excluded); when scoring a results folder, the time to read and score.
"""

from __future__ import annotations

import csv
import json
import logging
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from torchiid._version import __version__
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import TorchiidError
from torchiid.core.progress import progress
from torchiid.eval.datasets import DATASETS, EvalDataset, Sample, check_dataset, open_dataset
from torchiid.eval.methods import BASELINES, METHODS, method_parameters, run_method
from torchiid.eval.options import OPTION_NAMES, EvalOptions
from torchiid.eval.outputs import (
    SETTINGS,
    EvalResult,
    csv_row,
    default_output_dir,
    finite_or_none,
    means,
    prepare_output,
    write_json,
)
from torchiid.eval.results import (
    LAYERS,
    check_results_folder,
    input_decoding,
    load_layer,
)
from torchiid.eval.scoring import COUNT_COLUMNS, METRICS, pooled_saw_ap, score_sample

__all__ = [
    "BASELINES",
    "COUNT_COLUMNS",
    "DATASETS",
    "EvalOptions",
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


#: what an id is in each dataset (for messages)
_ID_NAMES = {
    "iiw": "IIW photo id",
    "mit": "MIT object name",
    "saw": "SAW photo id",
    "dense": "image name",
}

#: the note on layers that look decomposed from the wrongly decoded input
_DECODING_NOTES = {
    "srgb": (
        "look decomposed from the image read as sRGB, but this dataset's images are linear: "
        "decompose them with torchiid decompose --linear"
    ),
    "linear": (
        "look decomposed from the photo read as linear (--linear), but this dataset's photos "
        "are sRGB: decompose them without --linear"
    ),
}


def _method_mask(dataset: str, sample: Sample) -> torch.Tensor | None:
    """The mask the method runs under: the object mask (mit, dense), else the whole photo."""
    return sample.mask if dataset in ("mit", "dense") else None


def _guard(sample_id: str, fn: Callable[[], Any], fail: Callable[[str, Exception], None]) -> Any:
    """Call ``fn``; a :class:`TorchiidError` is recorded against the image and gives ``None``."""
    try:
        return fn()
    except TorchiidError as exc:
        fail(sample_id, exc)
        return None


def _log_failure(sample_id: str, exc: Exception) -> None:
    log.warning("%s: %s", sample_id, exc)


class EvalRunner:
    """Score a method (or a folder of decompositions) on an evaluation dataset.

    Construction checks the arguments and resolves the device; :meth:`run` does the work
    (see the module docstring for the output files, resuming and batching). The fields of
    :attr:`options` read as the runner's attributes too (``runner.batch_size``).

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"``.
        root: the dataset directory.
        options: how the run goes (default: ``EvalOptions()``, the ``semantic`` method);
            :func:`run_evaluation` takes its fields as keywords.

    Attributes:
        dataset: the dataset layout.
        root: the dataset directory.
        options: the :class:`EvalOptions`.
        method: the method run, ``"results"`` when scoring a results folder.
        output: the output folder.
        results_dir: the results folder scored, or ``None``.
        device: the resolved :class:`torch.device`.
        on_failure: what is called when an image fails.

    Raises:
        ParameterError: unknown dataset, or an option out of range (see
            :class:`EvalOptions`).
        TorchiidError: ``results_dir`` is not a directory, ``root`` is a file, or CUDA was
            asked for and is unavailable.

    Example:
        A run from Python (the dataset folder is the MIT-Berkeley release)::

            options = EvalOptions(method="r=i", output="eval-mit")
            result = EvalRunner("mit", "mit-berkeley", options).run()
            print(result.summary["mean"]["lmse"], result.failures)
    """

    def __init__(
        self,
        dataset: str,
        root: str | Path,
        options: EvalOptions | None = None,
    ) -> None:
        check_dataset(dataset)
        self.options = options if options is not None else EvalOptions()
        o = self.options
        self.results_dir = None if o.results_dir is None else Path(o.results_dir)
        if self.results_dir is not None and not self.results_dir.is_dir():
            raise TorchiidError(f"results directory {self.results_dir} does not exist")
        self.dataset = dataset
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise TorchiidError(f"{self.root}: is a file, not a {dataset} dataset directory")
        self.method = "results" if self.results_dir is not None else o.method
        self.output = (
            Path(o.output) if o.output is not None else default_output_dir(dataset, self.method)
        )
        self.device = o.device if isinstance(o.device, torch.device) else resolve_device(o.device)
        self.on_failure = o.on_failure if o.on_failure is not None else _log_failure

    def __getattr__(self, name: str) -> Any:
        # only called when the normal lookup fails: the options' other fields
        if name in OPTION_NAMES and "options" in self.__dict__:
            return getattr(self.options, name)
        raise AttributeError(f"'EvalRunner' object has no attribute {name!r}")

    def settings(self) -> dict[str, Any]:
        """The run's settings as ``summary.json`` records them (a resumed run must match)."""
        scoring = self.results_dir is not None
        o = self.options
        settings = {
            "dataset": self.dataset,
            "dir": str(self.root.resolve()),
            "method": self.method,
            "results_dir": str(self.results_dir.resolve()) if scoring else None,
            "input": o.input if self.dataset == "mit" else None,
            "delta": o.delta if self.dataset == "iiw" else None,
            "parameters": {} if scoring else method_parameters(self.method, o.params),
        }
        return json.loads(json.dumps(settings))  # as summary.json will hold them

    def run(self) -> EvalResult:
        """Evaluate every selected image and write the output folder.

        Images that fail (unreadable files, a method error, missing result layers: any
        :class:`TorchiidError`) are reported to ``on_failure`` and listed in the summary;
        the others are scored. ``summary.json`` is rewritten at the end, also when the run
        is interrupted (``status`` ``"stopped"``).

        Returns:
            The outcome as an ``EvalResult``, whose ``rows`` are ``{id: {column: value}}``
            and whose ``summary`` is what ``summary.json`` holds (also ``failures``, ``notes``).

        Raises:
            DatasetError: the dataset cannot be opened.
            TorchiidError: the output folder holds an incompatible run (other settings or
                columns, rows of ids outside this run's selection, or ``resume=False`` with
                an existing ``results.csv``), or the results folder holds no layer of any
                selected id.
        """
        o = self.options
        reader = open_dataset(self.dataset, self.root, o.ids, input=o.input)
        ids = list(reader.ids)[: o.limit]
        if self.results_dir is not None:
            check_results_folder(self.results_dir, ids, _ID_NAMES[self.dataset])
        columns = ["id", *METRICS[self.dataset], "seconds"]
        settings = self.settings()
        done = prepare_output(
            self.output, settings, columns, resume=o.resume, overwrite=o.overwrite, ids=ids
        )
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
        self.options = runner.options
        self.reader = reader
        self.ids = ids
        self.columns = columns
        self.settings = settings
        self.out = runner.output
        self.rows = {i: done[i] for i in ids if i in done}
        self.failures: dict[str, str] = {}
        self.decoding: dict[str, list[str]] = {}
        self.started = time.strftime("%Y-%m-%dT%H:%M:%S")
        self.csv_file: Any = None
        self.writer: Any = None
        self.bar: Any = None

    def summary(self, status: str) -> dict[str, Any]:
        ids, rows = self.ids, self.rows
        scored = [i for i in ids if i in rows]
        data = {
            "torchiid_version": __version__,
            **self.settings,
            "status": status,
            "started": self.started,
            "device": str(self.runner.device),
            "n_images": len(ids),
            "n_scored": len(scored),
            "mean": means(scored, rows, self.columns[1:-1]),
        }
        if self.runner.dataset == "saw":
            ap, n = pooled_saw_ap(self.out / "saw-scores", scored)
            data["pooled_ap"], data["pooled_ap_images"] = finite_or_none(ap), n
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
            delta=self.options.delta,
            saw_scores_dir=self.out / "saw-scores",
        )
        row["seconds"] = seconds
        self.writer.writerow(csv_row(sample.id, row, self.columns))
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
            layers = run_method(self.runner.method, image, mask, self.options.params)
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
        results = self.runner.results_dir
        assert results is not None  # scoring a results folder
        size = tuple(sample.image.shape[-2:])
        refl, shading = (load_layer(results, sample.id, layer, size) for layer in LAYERS)
        self.record(sample, refl, shading, time.perf_counter() - t0)
        mask = _method_mask(self.runner.dataset, sample)
        decoding = input_decoding(sample.image, refl, shading, mask)
        if decoding is not None:
            self.decoding.setdefault(decoding, []).append(sample.id)

    def notes(self) -> tuple[str, ...]:
        notes = []
        for decoding, ids in self.decoding.items():
            shown = ", ".join(ids[:5]) + (f" and {len(ids) - 5} more" if len(ids) > 5 else "")
            notes.append(
                f"the layers of {shown} in {self.runner.results_dir} {_DECODING_NOTES[decoding]}"
            )
        return tuple(notes)

    def loop(self) -> None:
        batch_size = self.options.batch_size
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
        write_json(self.out / "summary.json", self.summary("running"))
        self.bar = progress(
            len(self.ids),
            f"eval {self.runner.dataset}",
            "img",
            show=self.options.progress,
            initial=len(self.rows),
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
            write_json(self.out / "summary.json", data)
        return EvalResult(
            ids=tuple(self.ids),
            columns=tuple(self.columns),
            rows={i: self.rows[i] for i in self.ids if i in self.rows},
            failures=dict(self.failures),
            summary=data,
            output=self.out,
            notes=self.notes(),
        )


def run_evaluation(dataset: str, root: str | Path, **options: Any) -> EvalResult:
    """Shorthand for ``EvalRunner(dataset, root, EvalOptions(**options)).run()``.

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"``.
        root: the dataset directory.
        **options: the fields of :class:`EvalOptions` (``method``, ``params``, ``output``,
            ``results_dir``, ``device``, ``batch_size``, ...).

    Returns:
        The outcome as an ``EvalResult`` (see :class:`EvalResult`); ``result.rows`` holds the
        rows, ``result.summary`` the summary (a result does not unpack into the two).

    Example:
        The rows and the summary of a run::

            result = run_evaluation("mit", "mit-berkeley", method="r=i", output="eval-mit")
            rows, summary = result.rows, result.summary
    """
    return EvalRunner(dataset, root, EvalOptions(**options)).run()
