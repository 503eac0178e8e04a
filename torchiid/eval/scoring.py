"""Scoring one decomposition against a dataset sample: which metrics each benchmark uses.

Metrics per dataset (all computed on **linear** layers):

- ``iiw``: WHDR at margin ``δ`` (:func:`torchiid.eval.whdr`) of the reflectance.
- ``mit``: the MIT score ``½·LMSE(S) + ½·LMSE(gray R)`` (:func:`torchiid.eval.mit_lmse`) and
  its two halves, inside the object mask.
- ``saw``: shading average precision. AP pools the labelled pixels of every image, so a
  per-image score holds the image's own AP and its pixel counts; the pixels' scores can be
  saved (``<dir>/<id>.npz``) and pooled over images with :func:`pooled_saw_ap`.
- ``dense``: si-MSE, LMSE and (scale-invariant) DSSIM of reflectance and shading.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.eval.datasets import DATASETS, DenseSample, IIWSample, SAWSample, check_dataset
from torchiid.eval.dense import dssim, si_mse
from torchiid.eval.lmse import local_mse, mit_lmse
from torchiid.eval.saw import average_precision, saw_scores
from torchiid.eval.whdr import whdr

__all__ = ["COUNT_COLUMNS", "DATASETS", "METRICS", "pooled_saw_ap", "score_sample"]

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
"""The per-image scores of each dataset, in column order."""

COUNT_COLUMNS = ("n_smooth", "n_boundary")
"""Scores that are pixel counts (integers), not metrics."""


def _gray(x: torch.Tensor) -> torch.Tensor:
    return x.mean(dim=1, keepdim=True) if x.shape[1] != 1 else x


def score_sample(
    dataset: str,
    sample: IIWSample | DenseSample | SAWSample,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    *,
    delta: float = 0.10,
    saw_scores_dir: str | Path | None = None,
) -> dict[str, float]:
    """The metrics of one image (the columns :data:`METRICS` ``[dataset]``).

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"``.
        sample: the dataset's sample of the image (with ground truth).
        reflectance: ``(1, 3, H, W)`` estimate, linear, on the sample's device (CPU).
        shading: ``(1, C, H, W)`` estimate, linear; a 3-channel shading is reduced to gray
            where the ground truth is gray.
        delta: WHDR equality margin (``iiw``).
        saw_scores_dir: ``saw`` only: if given, the folder (created if missing; its parent
            must exist) where the image's pixel scores and targets go, as
            ``<id>.npz``, for :func:`pooled_saw_ap`.

    Returns:
        ``{metric: value}``; for ``saw`` the counts ``n_smooth``/``n_boundary`` are ints.

    Raises:
        ShapeError: a layer's size differs from the image's.
        ParameterError: unknown ``dataset``.
    """
    check_dataset(dataset)
    size = tuple(sample.image.shape[-2:])
    for name, x in (("reflectance", reflectance), ("shading", shading)):
        if tuple(x.shape[-2:]) != size:
            raise ShapeError(f"{name} is {tuple(x.shape[-2:])} but the image is {size}")
    if dataset == "iiw":
        return {"whdr": whdr(reflectance[0], sample.judgements, delta=delta)}
    if dataset == "saw":
        scores, targets = saw_scores(shading[0], sample.labels)
        if saw_scores_dir is not None:
            target_dir = Path(saw_scores_dir)
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
    if dataset == "mit":
        return {
            "lmse": float(mit_lmse(true_r, true_s, reflectance, shading, mask)[0]),
            "lmse_shading": float(local_mse(_gray(true_s), _gray(shading), mask)[0]),
            "lmse_reflectance": float(local_mse(_gray(true_r), _gray(reflectance), mask)[0]),
        }
    est_s = _gray(shading) if true_s.shape[1] == 1 else shading.expand_as(true_s)
    row = {}
    for name, gt, est in (("reflectance", true_r, reflectance), ("shading", true_s, est_s)):
        row[f"si_mse_{name}"] = float(si_mse(gt, est, mask)[0])
        row[f"lmse_{name}"] = float(local_mse(gt, est, mask)[0])
        row[f"dssim_{name}"] = float(dssim(gt, est, mask=mask, scale_invariant=True)[0])
    return row


def pooled_saw_ap(saw_scores_dir: str | Path, ids: Iterable[str]) -> tuple[float, int]:
    """SAW average precision pooled over the saved pixel scores of several images.

    Args:
        saw_scores_dir: the folder :func:`score_sample` wrote ``<id>.npz`` files to.
        ids: the images to pool; ids without a file are skipped.

    Returns:
        ``(ap, n_images)``: the AP over every pooled pixel (``nan`` when no file was found)
        and the number of images pooled.
    """
    scores, targets = [], []
    for i in ids:
        path = Path(saw_scores_dir) / f"{i}.npz"
        if path.is_file():
            with np.load(path) as data:
                scores.append(torch.from_numpy(data["scores"]))
                targets.append(torch.from_numpy(data["targets"]))
    if not scores:
        return math.nan, 0
    return float(average_precision(torch.cat(scores), torch.cat(targets))), len(scores)
