"""Shading average precision on Shading Annotations in the Wild (SAW).

Kovacs, Bell, Snavely & Bala, "Shading Annotations in the Wild", CVPR 2017, Section 5.
A good shading layer is smooth where annotators marked smooth shading and changes at shadow
boundaries and normal/depth discontinuities. Pixels are ranked by ``−|∇ log S|`` and the
average precision of finding the smooth-shading pixels is reported.

Variant implemented (the choices that make published SAW numbers differ):

- Gray shading (channel mean), floored at ``1e-4``, then ``log`` (as the authors' code).
- Gradient magnitude ``hypot(sobel_x, sobel_y)`` with the unnormalised 3×3 Sobel kernels
  and edge-replicated borders (scipy's ``sobel`` default; the scale does not affect a
  ranking). No smoothing.
- Boundary tolerance ("ignore boundary" dilation): a *negative* pixel (shadow boundary or
  normal discontinuity) is scored with the maximum gradient in a ``(2r+1)×(2r+1)``
  neighbourhood, ``r = boundary_radius`` (default 5, i.e. 11×11, close to the authors'
  ``bl_filter_size = 10``), because annotated boundaries are a few pixels off the true edge;
  positive (smooth) pixels use their own gradient. ``boundary_radius = 0`` switches it off.
- Unweighted: every labelled pixel counts once (the paper's ``P(u)``, not the
  gradient-weighted "challenge" ``P(c)``), and pixels of all images are pooled.
- AP is computed exactly from the ranking, ``AP = Σ_k (R_k − R_{k−1})·P_k`` over distinct
  score thresholds (scikit-learn's ``average_precision_score``), instead of the authors'
  trapezoid over 400 fixed thresholds with extrapolated end points.

Label convention (:data:`SAW_UNLABELED` … :data:`SAW_NORMAL`): 0 unlabeled (ignored),
1 smooth shading (positive), 2 shadow boundary, 3 normal/depth discontinuity (negatives).
The released ``.npy`` label maps use 2/1/0/100 instead; convert them with
:func:`torchiid.eval.datasets.saw_labels_from_release`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = [
    "SAW_UNLABELED",
    "SAW_SMOOTH",
    "SAW_SHADOW",
    "SAW_NORMAL",
    "average_precision",
    "saw_scores",
    "saw_ap",
]

SAW_UNLABELED = 0
SAW_SMOOTH = 1
SAW_SHADOW = 2
SAW_NORMAL = 3


def average_precision(scores: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Average precision of ranking ``targets`` (positives) by decreasing ``scores``.

    ``AP = Σ_k (R_k − R_{k−1}) P_k`` over the distinct score values taken as thresholds
    (tied scores enter together), as scikit-learn's ``average_precision_score``.

    Args:
        scores: ``(N,)`` higher means "more likely positive".
        targets: ``(N,)`` bool or {0, 1}.

    Returns:
        Scalar tensor (float64); ``nan`` when there is no positive.
    """
    s = scores.reshape(-1).double()
    t = targets.reshape(-1).to(torch.float64)
    if s.numel() != t.numel():
        raise ShapeError(f"scores has {s.numel()} elements but targets has {t.numel()}")
    n_pos = t.sum()
    if s.numel() == 0 or n_pos == 0:
        return torch.tensor(float("nan"), dtype=torch.float64)
    s, order = torch.sort(s, descending=True, stable=True)
    t = t[order]
    tp = torch.cumsum(t, 0)
    fp = torch.cumsum(1.0 - t, 0)
    # the last index of each run of equal scores is a threshold
    last = torch.ones_like(s, dtype=torch.bool)
    last[:-1] = s[1:] != s[:-1]
    tp, fp = tp[last], fp[last]
    precision = tp / (tp + fp)
    recall = tp / n_pos
    drecall = torch.diff(recall, prepend=recall.new_zeros(1))
    return (drecall * precision).sum()


def _shading_hw(shading: torch.Tensor) -> torch.Tensor:
    s = shading
    while s.dim() > 3 and s.shape[0] == 1:
        s = s[0]
    if s.dim() == 3:
        s = s.mean(dim=0)
    if s.dim() != 2:
        raise ShapeError(
            f"expected one shading of shape (H, W), (C, H, W) or (1, C, H, W), "
            f"got {tuple(shading.shape)}"
        )
    return s


def saw_scores(
    shading: torch.Tensor, labels: torch.Tensor, boundary_radius: int = 5
) -> tuple[torch.Tensor, torch.Tensor]:
    """Smoothness scores and targets of the labelled pixels of one image.

    Args:
        shading: linear shading estimate, ``(H, W)``, ``(C, H, W)`` or ``(1, C, H, W)``
            (channels averaged), at the label map's resolution.
        labels: ``(H, W)`` integer map in the convention of this module.
        boundary_radius: radius of the max filter applied to the gradient of negative pixels.

    Returns:
        ``(scores, targets)``, 1-D over labelled pixels: ``−|∇ log S|`` and ``True`` for
        smooth-shading pixels.
    """
    if boundary_radius < 0:
        raise ParameterError(f"expected boundary_radius >= 0, got {boundary_radius}")
    s = _shading_hw(shading)
    if labels.shape != s.shape:
        raise ShapeError(
            f"labels have shape {tuple(labels.shape)} but shading is {tuple(s.shape)}; "
            "resize the shading to the label map's resolution first"
        )
    logs = torch.log(s.double().clamp_min(1e-4))[None, None]
    p = F.pad(logs, (1, 1, 1, 1), mode="replicate")[0, 0]
    # separable Sobel: central difference first (exactly 0 on flat regions), then [1, 2, 1]
    dx = p[:, 2:] - p[:, :-2]
    dx = dx[:-2] + 2 * dx[1:-1] + dx[2:]
    dy = p[2:] - p[:-2]
    dy = dy[:, :-2] + 2 * dy[:, 1:-1] + dy[:, 2:]
    grad = torch.hypot(dx, dy)[None, None]
    if boundary_radius > 0:
        k = 2 * boundary_radius + 1
        grad_max = F.max_pool2d(grad, k, stride=1, padding=boundary_radius)
    else:
        grad_max = grad
    lab = labels.to(grad.device)
    positive = lab == SAW_SMOOTH
    negative = (lab == SAW_SHADOW) | (lab == SAW_NORMAL)
    g = torch.where(negative, grad_max[0, 0], grad[0, 0])
    keep = positive | negative
    return -g[keep], positive[keep]


def saw_ap(
    shading: torch.Tensor | Sequence[torch.Tensor],
    labels: torch.Tensor | Sequence[torch.Tensor],
    boundary_radius: int = 5,
) -> float:
    """SAW shading average precision (unweighted, pixels pooled over images).

    Args:
        shading: one shading (see :func:`saw_scores`) or a sequence of them.
        labels: the matching label map(s), ``(H, W)``.
        boundary_radius: see the module docstring; 0 disables the boundary tolerance.

    Returns:
        AP in ``[0, 1]`` (``nan`` without smooth-shading pixels).
    """
    if isinstance(shading, torch.Tensor):
        shading, labels = [shading], [labels]  # type: ignore[list-item]
    if len(shading) != len(labels):
        raise ShapeError(f"got {len(shading)} shadings but {len(labels)} label maps")
    pairs = [saw_scores(s, lab, boundary_radius) for s, lab in zip(shading, labels, strict=True)]
    if not pairs:
        raise ShapeError("expected at least one shading / label map pair")
    scores = torch.cat([p[0].cpu() for p in pairs])
    targets = torch.cat([p[1].cpu() for p in pairs])
    return float(average_precision(scores, targets))
