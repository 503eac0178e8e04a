"""Weighted human disagreement rate (WHDR) on Intrinsic Images in the Wild judgements.

Bell, Bala & Snavely, "Intrinsic Images in the Wild", SIGGRAPH 2014, Section 5. The metric
compares the reflectance estimate at pairs of points with crowd judgements of which point
is darker (δ = 0.10; the documentation's Evaluation guide).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["whdr", "load_judgements"]


def load_judgements(judgements: Mapping[str, Any] | str | Path) -> Mapping[str, Any]:
    """Return an IIW judgement dict, reading it from a JSON file when given a path.

    Raises:
        ParameterError: the file cannot be read or lacks ``intrinsic_points`` /
            ``intrinsic_comparisons``.
    """
    if isinstance(judgements, (str, Path)):
        path = Path(judgements)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ParameterError(f"cannot read IIW judgements from {path}: {exc}") from exc
    else:
        data = judgements
    if not isinstance(data, Mapping):
        raise ParameterError(f"expected IIW judgements as a dict, got {type(data).__name__}")
    for key in ("intrinsic_points", "intrinsic_comparisons"):
        if key not in data:
            raise ParameterError(f"IIW judgements lack the key {key!r}")
    return data


def _reflectance_hw3(reflectance: np.ndarray | torch.Tensor) -> np.ndarray:
    """Bring a reflectance to a float64 ``(H, W, C)`` numpy array."""
    if isinstance(reflectance, torch.Tensor):
        r = reflectance.detach().to("cpu", torch.float64)
        if r.dim() == 4:
            if r.shape[0] != 1:
                raise ShapeError(
                    f"expected reflectance of shape (1, C, H, W), got {tuple(r.shape)}"
                )
            r = r[0]
        if r.dim() == 2:
            r = r[None]
        if r.dim() != 3:
            raise ShapeError(f"expected reflectance tensor (C, H, W), got {tuple(r.shape)}")
        return r.permute(1, 2, 0).numpy()
    arr = np.asarray(reflectance, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise ShapeError(f"expected reflectance array (H, W, C), got {arr.shape}")
    return arr


def whdr(
    reflectance: np.ndarray | torch.Tensor,
    judgements: Mapping[str, Any] | str | Path,
    delta: float = 0.10,
) -> float:
    """Weighted human disagreement rate of a reflectance estimate (Bell et al. 2014).

    For every comparison whose ``darker`` is one of ``'1'``, ``'2'``, ``'E'``, whose
    ``darker_score`` is positive and whose two points are both ``opaque``, the reflectance is
    read at row ``int(y * rows)``, column ``int(x * cols)`` (clamped to the last row/column for
    ``y == 1`` or ``x == 1``), reduced to gray by the channel mean and floored at ``1e-10``.
    The algorithm's answer is ``'1'`` (point 1 darker) if ``l2 / l1 > 1 + delta``, ``'2'`` if
    ``l1 / l2 > 1 + delta`` and ``'E'`` otherwise; ``WHDR = Σ w·[answer ≠ darker] / Σ w``
    with ``w = darker_score``.

    Args:
        reflectance: linear RGB reflectance, ``(H, W, 3)`` numpy array or ``(3, H, W)`` /
            ``(1, 3, H, W)`` tensor (gray ``(H, W)`` / ``(1, H, W)`` also accepted). The metric
            is invariant to a global scale.
        judgements: the IIW JSON content (dict) or a path to ``<id>.json``.
        delta: the equality margin δ (0.10 in Bell et al.).

    Returns:
        The WHDR in ``[0, 1]``; ``nan`` when no comparison qualifies.

    Shape:
        - reflectance: ``(H, W, C)`` array or ``(C, H, W)`` / ``(1, C, H, W)`` tensor.
    """
    if not delta >= 0:
        raise ParameterError(f"expected delta >= 0, got {delta}")
    data = load_judgements(judgements)
    refl = _reflectance_hw3(reflectance)
    rows, cols = refl.shape[:2]
    gray = np.maximum(refl.mean(axis=2), 1e-10)
    points = {p["id"]: p for p in data["intrinsic_points"]}

    error_sum = 0.0
    weight_sum = 0.0
    for c in data["intrinsic_comparisons"]:
        darker = c.get("darker")
        if darker not in ("1", "2", "E"):
            continue
        weight = c.get("darker_score")
        if weight is None or weight <= 0:
            continue
        p1, p2 = points[c["point1"]], points[c["point2"]]
        if not (p1.get("opaque") and p2.get("opaque")):
            continue
        l1 = gray[min(int(p1["y"] * rows), rows - 1), min(int(p1["x"] * cols), cols - 1)]
        l2 = gray[min(int(p2["y"] * rows), rows - 1), min(int(p2["x"] * cols), cols - 1)]
        if l2 / l1 > 1.0 + delta:
            answer = "1"
        elif l1 / l2 > 1.0 + delta:
            answer = "2"
        else:
            answer = "E"
        if answer != darker:
            error_sum += weight
        weight_sum += weight
    return error_sum / weight_sum if weight_sum > 0 else math.nan
