"""``torchiid eval``: score a method (or a folder of results) on an evaluation dataset.

Metrics per dataset (all computed on **linear** layers):

- ``iiw``: WHDR at margin ``δ`` (:func:`torchiid.eval.whdr`) of the reflectance.
- ``mit``: the MIT score ``½·LMSE(S) + ½·LMSE(gray R)`` (:func:`torchiid.eval.mit_lmse`) and
  its two halves, inside the object mask.
- ``saw``: shading average precision. AP pools the labelled pixels of every image, so the
  per-image rows hold the image's own AP and its pixel counts, the pixels' scores go to
  ``saw-scores/<id>.npz`` and ``summary.json`` holds the pooled AP over all of them.
- ``dense``: si-MSE, LMSE and (scale-invariant) DSSIM of reflectance and shading.

Outputs in the output folder: ``results.csv`` (a row per image, appended and flushed as
images finish, so an interrupted run resumes where it stopped) and ``summary.json``
(settings, parameters, means, median seconds per image, failures).
"""

from __future__ import annotations

import argparse
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchiid.commands.decompose import add_parameter_options, params_from_args
from torchiid.core.exceptions import ParameterError, ShapeError, TorchiidError

__all__ = ["add_eval_parser", "run_eval", "METRICS"]

log = logging.getLogger("torchiid")

DATASETS = ("iiw", "mit", "saw", "dense")
METHODS = ("semantic", "retinex", "r=i", "s=i")
METRICS: dict[str, tuple[str, ...]] = {
    "iiw": ("whdr",),
    "mit": ("lmse", "lmse_shading", "lmse_reflectance"),
    "saw": ("ap", "n_smooth", "n_boundary"),
    "dense": (
        "si_mse_reflectance",
        "si_mse_shading",
        "lmse_reflectance",
        "lmse_shading",
        "dssim_reflectance",
        "dssim_shading",
    ),
}
COUNT_COLUMNS = ("n_smooth", "n_boundary")
SETTINGS = ("dataset", "dir", "method", "results_dir", "input", "delta", "parameters")

EPILOG = """\
results folder (--results DIR): instead of running a method, read the layers of every
dataset id from DIR, the exact files first: <id>-reflectance.npy and <id>-shading.npy
(float32 linear, `torchiid decompose --save-npy`), else <id>-reflectance-linear16.png and
<id>-shading.exr (16-bit linear and float OpenEXR, written by `torchiid decompose`), else
<id>-reflectance.png and <id>-shading.png (8-bit sRGB, decoded to linear). The id is the
IIW/SAW photo id, the MIT object name, or the dense image name; the layers must have the
image's size.

resuming: results.csv gets a row as each image finishes. With --resume (the default) the
ids already in it are skipped and counted in the summary; the run's settings must match
those in summary.json. --no-resume refuses to touch an existing results.csv; --overwrite
discards it and starts over. Failed images get no row, so a resumed run retries them.

batching: images of equal size are decomposed together in batches of --batch-size (at
most 4 x batch-size images wait in memory for a partner of their size).

seconds (results.csv): the method's wall time per image (a batch's time divided by its
size; dataset reading and scoring excluded); with --results, the time to read and score.

exit status: 0 when every image was scored, 1 when some failed, 2 on a usage error."""


def add_eval_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``eval`` subcommand to ``subparsers`` (from ``add_subparsers``)."""
    p = subparsers.add_parser(
        "eval",
        help="score a method on IIW, MIT-Berkeley, SAW or a dense-GT folder",
        description="Decompose every image of an evaluation dataset (or read an existing "
        "results folder) and score it: WHDR (iiw), LMSE (mit), shading AP (saw), "
        "si-MSE / LMSE / DSSIM (dense). Prints a per-image and mean table and "
        "writes results.csv and summary.json.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", choices=DATASETS, help="which benchmark layout DIR has")
    p.add_argument("dir", type=Path, metavar="DIR", help="the dataset directory")
    p.add_argument(
        "-o", "--output", type=Path, help="output folder (default: ./eval-<dataset>-<method>)"
    )
    p.add_argument(
        "--method",
        default="semantic",
        choices=METHODS,
        help="semantic: the paper's method (default); retinex: colour Retinex; "
        "r=i: reflectance = image, shading = 1; s=i: shading = gray image, "
        "reflectance = 1 (reference rows)",
    )
    add_parameter_options(p)
    p.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="where to run (auto: CUDA when available)",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=1,
        help="images of equal size decomposed together (default 1)",
    )
    p.add_argument("--limit", type=int, help="evaluate only the first N images of the set")
    p.add_argument(
        "--ids", type=Path, help="file of ids to evaluate, one a line (e.g. an IIW/SAW test split)"
    )
    p.add_argument(
        "--input",
        default="diffuse",
        choices=["diffuse", "original"],
        help="MIT input image (default diffuse, the standard protocol)",
    )
    p.add_argument(
        "--results",
        type=Path,
        metavar="DIR",
        help="score the decompositions in DIR instead of running --method (see below)",
    )
    p.add_argument(
        "--resume",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="skip the ids already in OUT/results.csv (default: on)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="discard existing results in the output folder and start over",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--delta", type=float, default=0.10, help="WHDR equality margin (iiw)")
    return p


# --------------------------------------------------------------------------- datasets


def _open_dataset(args: argparse.Namespace):
    from torchiid.eval.datasets import (
        DenseFolderDataset,
        IIWDataset,
        MITDataset,
        SAWDataset,
        read_id_list,
    )

    ids = read_id_list(args.ids) if args.ids is not None else None
    if args.dataset == "iiw":
        return IIWDataset(args.dir, ids=ids)
    if args.dataset == "mit":
        return MITDataset(args.dir, objects=ids, input=args.input)
    if args.dataset == "saw":
        return SAWDataset(args.dir, ids=ids)
    ds = DenseFolderDataset(args.dir)
    if ids is not None:
        from torchiid.eval.datasets import DatasetError

        missing = sorted(set(ids) - set(ds.ids))
        if missing:
            raise DatasetError(
                f"{len(missing)} ids of {args.ids} are not in {args.dir}: {missing[:5]}"
            )
        ds.ids = tuple(ids)
    return ds


def _eval_mask(dataset: str, sample) -> torch.Tensor | None:
    """The mask the method runs under: the object mask (mit, dense), else the whole photo."""
    return sample.mask if dataset in ("mit", "dense") else None


# --------------------------------------------------------------------------- methods


def _run_method(
    method: str, image: torch.Tensor, mask: torch.Tensor | None, params
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(reflectance (B, 3, H, W), shading (B, 1, H, W))`` of linear ``image`` (B, 3, H, W)."""
    if method == "r=i":
        return image.clone(), image.new_ones(image.shape[0], 1, *image.shape[-2:])
    if method == "s=i":
        return torch.ones_like(image), image.mean(dim=1, keepdim=True)
    if method == "retinex":
        from torchiid.baselines.retinex import color_retinex

        return color_retinex(image, mask=mask)
    from torchiid import model

    out = model.decompose(image, params, mask=mask)
    return out.reflectance, out.shading


def _method_parameters(method: str, params) -> dict[str, Any]:
    if method == "semantic":
        return params.to_dict()
    if method == "retinex":
        from torchiid.baselines.retinex import color_retinex

        sig = inspect.signature(color_retinex).parameters.values()
        return {
            p.name: p.default
            for p in sig
            if p.default is not inspect.Parameter.empty and p.name != "mask"
        }
    return {}


def _load_layer(results: Path, sample_id: str, layer: str) -> torch.Tensor:
    """One layer of a results folder as ``(1, C, H, W)`` linear.

    The exact files are preferred: ``<id>-<layer>.npy`` (float32), then
    ``<id>-reflectance-linear16.png`` / ``<id>-shading.exr``, and only then the viewable 8-bit
    sRGB ``<id>-<layer>.png``.
    """
    from torchiid.io import load_image

    exact = "reflectance-linear16.png" if layer == "reflectance" else "shading.exr"
    candidates = [
        (results / f"{sample_id}-{layer}.npy", False),
        (results / f"{sample_id}-{exact}", True),
        (results / f"{sample_id}-{layer}.png", False),
    ]
    for path, linear in candidates:
        if path.is_file():
            img = load_image(path, linear=linear, alpha="ignore", min_side=1).image
            return (img.mean(dim=0, keepdim=True) if layer == "shading" else img)[None]
    names = ", ".join(p.name for p, _ in candidates)
    raise TorchiidError(f"{results}: none of {names}")


# --------------------------------------------------------------------------- scoring


def _gray(x: torch.Tensor) -> torch.Tensor:
    return x.mean(dim=1, keepdim=True) if x.shape[1] != 1 else x


def _score(
    args: argparse.Namespace, out_dir: Path, sample, refl: torch.Tensor, shading: torch.Tensor
) -> dict[str, float]:
    """Metrics of one image; ``refl`` ``(1, 3, H, W)`` and ``shading`` ``(1, C, H, W)``, linear."""
    from torchiid.eval import average_precision, dssim, local_mse, mit_lmse, saw_scores, si_mse
    from torchiid.eval import whdr as whdr_fn

    size = tuple(sample.image.shape[-2:])
    for name, x in (("reflectance", refl), ("shading", shading)):
        if tuple(x.shape[-2:]) != size:
            raise ShapeError(f"{name} is {tuple(x.shape[-2:])} but the image is {size}")
    if args.dataset == "iiw":
        return {"whdr": whdr_fn(refl[0], sample.judgements, delta=args.delta)}
    if args.dataset == "saw":
        scores, targets = saw_scores(shading[0], sample.labels)
        target_dir = out_dir / "saw-scores"
        target_dir.mkdir(exist_ok=True)
        tmp = target_dir / f".{sample.id}.tmp.npz"
        np.savez(tmp, scores=scores.numpy(), targets=targets.numpy())
        os.replace(tmp, target_dir / f"{sample.id}.npz")
        n_smooth = int(targets.sum())
        return {
            "ap": float(average_precision(scores, targets)),
            "n_smooth": n_smooth,
            "n_boundary": int(targets.numel()) - n_smooth,
        }
    mask = sample.mask[None]
    true_r, true_s = sample.reflectance[None], sample.shading[None]
    if args.dataset == "mit":
        return {
            "lmse": float(mit_lmse(true_s, true_r, shading, refl, mask)[0]),
            "lmse_shading": float(local_mse(_gray(true_s), _gray(shading), mask)[0]),
            "lmse_reflectance": float(local_mse(_gray(true_r), _gray(refl), mask)[0]),
        }
    est_s = _gray(shading) if true_s.shape[1] == 1 else shading.expand_as(true_s)
    row = {}
    for name, gt, est in (("reflectance", true_r, refl), ("shading", true_s, est_s)):
        row[f"si_mse_{name}"] = float(si_mse(gt, est, mask)[0])
        row[f"lmse_{name}"] = float(local_mse(gt, est, mask)[0])
        row[f"dssim_{name}"] = float(dssim(gt, est, mask=mask, scale_invariant=True)[0])
    return row


def _pooled_ap(out_dir: Path, ids: list[str]) -> tuple[float, int]:
    from torchiid.eval import average_precision

    scores, targets = [], []
    for i in ids:
        path = out_dir / "saw-scores" / f"{i}.npz"
        if path.is_file():
            with np.load(path) as data:
                scores.append(torch.from_numpy(data["scores"]))
                targets.append(torch.from_numpy(data["targets"]))
    if not scores:
        return math.nan, 0
    return float(average_precision(torch.cat(scores), torch.cat(targets))), len(scores)


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
    out: Path, settings: dict[str, Any], columns: list[str], args: argparse.Namespace
) -> dict[str, dict[str, float]]:
    """Create / check the output folder; return the rows already done (when resuming)."""
    if out.exists() and not out.is_dir():
        raise TorchiidError(f"{out}: output exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    csv_path, summary_path = out / "results.csv", out / "summary.json"
    if args.overwrite:
        for p in (csv_path, summary_path):
            p.unlink(missing_ok=True)
        shutil.rmtree(out / "saw-scores", ignore_errors=True)
    elif csv_path.exists() and not args.resume:
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


# --------------------------------------------------------------------------- table


def _table(
    ids: list[str],
    rows: dict[str, dict[str, float]],
    columns: list[str],
    means: dict[str, float | None],
) -> str:
    width = max([len("mean"), len("id"), *(len(i) for i in ids)])
    cols = columns[1:]
    widths = [max(len(c), 10) for c in cols]
    head = f"{'id':<{width}}  " + "  ".join(f"{c:>{w}}" for c, w in zip(cols, widths, strict=True))

    def cell(c: str, v: float | None, w: int) -> str:
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return f"{'-':>{w}}"
        return f"{int(v):>{w}d}" if c in COUNT_COLUMNS else f"{v:>{w}.4f}"

    lines = [head, "-" * len(head)]
    for i in ids:
        r = rows[i]
        lines.append(
            f"{i:<{width}}  "
            + "  ".join(cell(c, r[c], w) for c, w in zip(cols, widths, strict=True))
        )
    lines.append("-" * len(head))
    lines.append(
        f"{'mean':<{width}}  "
        + "  ".join(cell(c, means.get(c), w) for c, w in zip(cols, widths, strict=True))
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------- run


def run_eval(args: argparse.Namespace) -> int:
    """Run the ``eval`` subcommand; returns the exit status (1 if any image failed)."""
    from tqdm import tqdm

    from torchiid.cli import resolve_device

    if args.batch_size < 1:
        raise ParameterError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.limit is not None and args.limit < 1:
        raise ParameterError(f"--limit must be >= 1, got {args.limit}")
    if not args.delta >= 0:
        raise ParameterError(f"--delta must be >= 0, got {args.delta}")
    scoring = args.results is not None
    if scoring and not args.results.is_dir():
        raise TorchiidError(f"results directory {args.results} does not exist")
    method = "results" if scoring else args.method
    params = None
    if method == "semantic":
        params = params_from_args(args)
    device = resolve_device(args.device)
    dataset = _open_dataset(args)
    ids = list(dataset.ids)[: args.limit]
    columns = ["id", *METRICS[args.dataset], "seconds"]
    settings = {
        "dataset": args.dataset,
        "dir": str(args.dir.resolve()),
        "method": method,
        "results_dir": str(args.results.resolve()) if scoring else None,
        "input": args.input if args.dataset == "mit" else None,
        "delta": args.delta if args.dataset == "iiw" else None,
        "parameters": {} if scoring else _method_parameters(method, params),
    }
    settings = json.loads(json.dumps(settings))  # as summary.json will hold them
    out: Path = args.output or Path(f"eval-{args.dataset}-{method}")
    done = _prepare_output(out, settings, columns, args)
    rows = {i: done[i] for i in ids if i in done}
    failures: dict[str, str] = {}
    started = time.strftime("%Y-%m-%dT%H:%M:%S")

    def summary(status: str) -> dict[str, Any]:
        scored = [i for i in ids if i in rows]
        means = {}
        for c in columns[1:-1]:
            vals = [rows[i][c] for i in scored if math.isfinite(rows[i][c])]
            means[c] = _finite_or_none(statistics.fmean(vals)) if vals else None
        data = {
            **settings,
            "status": status,
            "started": started,
            "device": str(device),
            "n_images": len(ids),
            "n_scored": len(scored),
            "mean": means,
        }
        if args.dataset == "saw":
            ap, n = _pooled_ap(out, scored)
            data["pooled_ap"], data["pooled_ap_images"] = _finite_or_none(ap), n
        times = [rows[i]["seconds"] for i in scored]
        data["median_seconds"] = statistics.median(times) if times else None
        data["failures"] = [{"id": i, "error": m} for i, m in failures.items()]
        return data

    _write_json(out / "summary.json", summary("running"))
    bar = tqdm(
        total=len(ids),
        initial=len(rows),
        desc=f"eval {args.dataset}",
        unit="img",
        disable=args.no_progress,
        file=sys.stderr,
        leave=False,
    )
    csv_file = (out / "results.csv").open("a", newline="")
    writer = csv.writer(csv_file)

    def record(sample, refl: torch.Tensor, shading: torch.Tensor, seconds: float) -> None:
        row = _score(args, out, sample, refl.detach().cpu().float(), shading.detach().cpu().float())
        row["seconds"] = seconds
        writer.writerow([sample.id, *(_fmt(c, row[c]) for c in columns[1:])])
        csv_file.flush()
        rows[sample.id] = row

    def fail(sample_id: str, exc: Exception) -> None:
        failures[sample_id] = str(exc)
        tqdm.write(f"torchiid: error: {sample_id}: {exc}", file=sys.stderr)

    def run_batch(samples: list) -> None:
        image = torch.stack([s.image for s in samples]).to(device)
        masks = [_eval_mask(args.dataset, s) for s in samples]
        mask = None if masks[0] is None else torch.stack(masks).to(device)
        t0 = time.perf_counter()
        try:
            refl, shading = _run_method(method, image, mask, params)
        except TorchiidError as exc:
            if len(samples) > 1:  # find the culprit: run them one by one
                for s in samples:
                    run_batch([s])
                return
            fail(samples[0].id, exc)
            bar.update(1)
            return
        seconds = (time.perf_counter() - t0) / len(samples)
        for k, s in enumerate(samples):
            _guard(
                s.id, lambda s=s, k=k: record(s, refl[k : k + 1], shading[k : k + 1], seconds), fail
            )
            bar.update(1)

    pending: dict[tuple[int, int], list] = {}
    status = "stopped"
    try:
        for sample_id in ids:
            if sample_id in rows:
                continue
            sample = _guard(sample_id, lambda i=sample_id: dataset.load(i), fail)
            if sample is None:
                bar.update(1)
                continue
            if scoring:
                t0 = time.perf_counter()

                def score_one(s=sample, t0=t0) -> None:
                    refl = _load_layer(args.results, s.id, "reflectance")
                    shading = _load_layer(args.results, s.id, "shading")
                    record(s, refl, shading, time.perf_counter() - t0)

                _guard(sample_id, score_one, fail)
                bar.update(1)
                continue
            group = pending.setdefault(tuple(sample.image.shape[-2:]), [])
            group.append(sample)
            if len(group) == args.batch_size:
                run_batch(pending.pop(tuple(sample.image.shape[-2:])))
            elif sum(len(g) for g in pending.values()) >= 4 * args.batch_size:
                run_batch(pending.pop(max(pending, key=lambda k: len(pending[k]))))
        for key in list(pending):
            run_batch(pending.pop(key))
        status = "complete"
    finally:
        csv_file.close()
        bar.close()
        data = summary(status)
        _write_json(out / "summary.json", data)
    scored = [i for i in ids if i in rows]
    print(_table(scored, rows, columns, data["mean"]))
    if args.dataset == "saw":
        ap = data["pooled_ap"]
        print(
            f"pooled AP over {data['pooled_ap_images']} images: "
            + ("-" if ap is None else f"{ap:.4f}")
        )
    if data["median_seconds"] is not None:
        print(f"median seconds per image: {data['median_seconds']:.3f}")
    print(f"wrote {out / 'results.csv'} and {out / 'summary.json'}")
    if failures:
        print(f"torchiid: {len(failures)} of {len(ids)} image(s) failed", file=sys.stderr)
        return 1
    return 0


def _guard(sample_id: str, fn: Callable[[], Any], fail: Callable[[str, Exception], None]):
    """Call ``fn``; a :class:`TorchiidError` is recorded against the image and gives ``None``."""
    try:
        return fn()
    except TorchiidError as exc:
        fail(sample_id, exc)
        return None
