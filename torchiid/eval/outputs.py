"""The output folder of an evaluation run: ``results.csv``, ``summary.json`` and their checks.

``results.csv`` holds a row per scored image (``id``, the dataset's metrics, ``seconds``) and
``summary.json`` the run's settings (:data:`SETTINGS`), status, means and failures; see
:mod:`torchiid.eval.runner` for how a run writes them and resumes from them.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchiid.core.exceptions import TorchiidError
from torchiid.eval.scoring import COUNT_COLUMNS

__all__ = ["SETTINGS", "EvalResult", "default_output_dir"]

SETTINGS = ("dataset", "dir", "method", "results_dir", "input", "delta", "parameters")
"""The ``summary.json`` keys a resumed run must match."""


def default_output_dir(dataset: str, method: str) -> Path:
    """``eval-<dataset>-<method>`` in the working directory (``method`` may be ``results``)."""
    return Path(f"eval-{dataset}-{method}")


@dataclass(frozen=True, eq=False)
class EvalResult:
    """The outcome of :meth:`~torchiid.eval.runner.EvalRunner.run`.

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
        notes: remarks on the run that are no failure, one line each: the layers of a
            results folder that look decomposed from the wrongly decoded input (see
            :func:`~torchiid.eval.results.input_decoding`); ``torchiid eval`` prints them as
            ``torchiid: note: ...``.

    Example:
        The rows and the summary of a run::

            result = run_evaluation("mit", "mit-berkeley", method="r=i", output="eval-mit")
            rows, summary = result.rows, result.summary
            print(rows["apple"]["lmse"], summary["mean"]["lmse"])
    """

    ids: tuple[str, ...]
    columns: tuple[str, ...]
    rows: dict[str, dict[str, float]]
    failures: dict[str, str]
    summary: dict[str, Any]
    output: Path
    notes: tuple[str, ...] = ()

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


def csv_row(sample_id: str, row: dict[str, float], columns: list[str]) -> list[str]:
    """A ``results.csv`` line: counts as integers, metrics as exact ``repr`` floats."""
    cells = (str(int(row[c])) if c in COUNT_COLUMNS else repr(float(row[c])) for c in columns[1:])
    return [sample_id, *cells]


def finite_or_none(v: float) -> float | None:
    """``v``, or ``None`` where JSON has no number for it (NaN, infinities)."""
    return v if math.isfinite(v) else None


def means(ids: list[str], rows: dict[str, dict[str, float]], metrics: list[str]) -> dict:
    """Each metric's mean over the finite values of ``ids`` (``None`` when there is none)."""
    out = {}
    for c in metrics:
        vals = [rows[i][c] for i in ids if math.isfinite(rows[i][c])]
        out[c] = finite_or_none(statistics.fmean(vals)) if vals else None
    return out


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` to ``path`` through a temporary file: a reader never sees half of it."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=False, allow_nan=False) + "\n")
    os.replace(tmp, path)


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


def _check_settings(out: Path, settings: dict[str, Any]) -> None:
    """Refuse to resume a run whose ``summary.json`` records other :data:`SETTINGS`."""
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        return
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


def _check_ids(out: Path, done: dict[str, dict[str, float]], ids: Sequence[str]) -> None:
    """Refuse to resume into a ``results.csv`` that holds rows of ids outside ``ids``.

    A resumed run may select more images than the run before it (``limit=2``, then all), not
    other or fewer: its summary describes its own selection, and ``results.csv`` would hold
    rows that the summary does not count.
    """
    selected = set(ids)
    extra = [i for i in done if i not in selected]
    if extra:
        shown = ", ".join(extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else "")
        raise TorchiidError(
            f"{out} holds a run with other settings (ids: its results.csv scores {shown}, "
            "which this run does not select); use another -o or --overwrite"
        )


def prepare_output(
    out: Path,
    settings: dict[str, Any],
    columns: list[str],
    *,
    resume: bool,
    overwrite: bool,
    ids: Sequence[str] | None = None,
) -> dict[str, dict[str, float]]:
    """Create / check the output folder; return the rows already done (when resuming).

    ``results.csv`` is rewritten with those rows alone, so a torn last line is gone before
    the run appends to it. With ``ids`` (the run's selection), rows of other ids are refused
    (see :func:`_check_ids`): ``results.csv`` and ``summary.json`` describe the same images.
    """
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
        _check_settings(out, settings)
        done = _read_rows(csv_path, columns)
        if ids is not None:
            _check_ids(out, done, ids)
    tmp = out / ".results.csv.tmp"
    with tmp.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for i, row in done.items():
            writer.writerow(csv_row(i, row, columns))
    os.replace(tmp, csv_path)
    return done
