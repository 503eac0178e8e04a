"""Dense ground-truth metrics (ARAP, MPI Sintel style): si-MSE, SSIM and DSSIM.

LMSE lives in :mod:`torchiid.eval.lmse`. All inputs are linear ``(B, C, H, W)`` tensors.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchiid.core.check import as_mask, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["scale_to_match", "si_mse", "ssim", "dssim"]


def _check_pair(gt: torch.Tensor, est: torch.Tensor) -> None:
    check_shape(gt, ("B", "C", "H", "W"), "gt")
    if est.shape != gt.shape:
        raise ShapeError(f"est has shape {tuple(est.shape)} but gt has shape {tuple(gt.shape)}")


def scale_to_match(
    gt: torch.Tensor, est: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Scale ``est`` per image and channel by ``α = Σ m·gt·est / Σ m·est²`` (0 if est is 0).

    Shape:
        - gt, est: ``(B, C, H, W)``; mask: ``(B, 1, H, W)`` or broadcastable; output like est.
    """
    _check_pair(gt, est)
    m = as_mask(mask, gt).double()
    g, e = gt.double(), est.double()
    den = (m * e * e).sum(dim=(2, 3), keepdim=True)
    num = (m * g * e).sum(dim=(2, 3), keepdim=True)
    alpha = torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)
    return (alpha * e).to(est.dtype)


def si_mse(gt: torch.Tensor, est: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Scale-invariant MSE (Grosse et al. 2009; the "MSE" of Sintel/ARAP tables).

    The estimate is scaled per image and channel by the least-squares ``α`` (see
    :func:`scale_to_match`); the error is the mean of ``(gt − α·est)²`` over masked pixels
    and channels, ``Σ_c Σ_p m_p (gt − α_c est)² / (C · Σ_p m_p)``.

    Returns:
        ``(B,)`` in the dtype of ``gt``.

    Shape:
        - gt, est: ``(B, C, H, W)``; mask: ``(B, 1, H, W)`` (bool or weights) or ``None``.
    """
    _check_pair(gt, est)
    m = as_mask(mask, gt).double()
    err = (m * (gt.double() - scale_to_match(gt, est, mask).double()) ** 2).sum(dim=(1, 2, 3))
    count = m.sum(dim=(1, 2, 3)) * gt.shape[1]
    return (err / count).to(gt.dtype)


def _gaussian_window(sigma: float, radius: int, like: torch.Tensor) -> torch.Tensor:
    x = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


def ssim(
    gt: torch.Tensor,
    est: torch.Tensor,
    data_range: float = 1.0,
    sigma: float = 1.5,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, own implementation.

    Local statistics use a separable Gaussian of std ``sigma`` truncated at radius
    ``int(3.5·sigma + 0.5)`` (11×11 for σ = 1.5), population (not sample) covariances,
    ``C1 = (0.01·L)²``, ``C2 = (0.03·L)²`` with ``L = data_range``. The SSIM map is computed
    on the valid region only (no padding, a border of ``radius`` pixels dropped), and
    averaged over channels and over the valid pixels (within ``mask`` if given). This equals
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=L)``.

    Returns:
        ``(B,)`` SSIM in ``[-1, 1]``, dtype of ``gt``.

    Shape:
        - gt, est: ``(B, C, H, W)``; mask: ``(B, 1, H, W)`` or ``None``.
    """
    _check_pair(gt, est)
    if not data_range > 0 or not sigma > 0:
        raise ParameterError(f"expected data_range > 0 and sigma > 0, got {data_range}, {sigma}")
    radius = int(3.5 * sigma + 0.5)
    b, c, h, w = gt.shape
    if h <= 2 * radius or w <= 2 * radius:
        raise ShapeError(f"image is {h}x{w}; SSIM with sigma={sigma} needs > {2 * radius} px")
    x, y = gt.double(), est.double()
    g = _gaussian_window(sigma, radius, x)
    kh = g.view(1, 1, -1, 1)
    kw = g.view(1, 1, 1, -1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        t = t.reshape(b * c, 1, h, w)
        return F.conv2d(F.conv2d(t, kh), kw).reshape(b, c, h - 2 * radius, w - 2 * radius)

    mx, my = blur(x), blur(y)
    vx = blur(x * x) - mx * mx
    vy = blur(y * y) - my * my
    cxy = blur(x * y) - mx * my
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    smap = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    m = as_mask(mask, gt).double()[..., radius : h - radius, radius : w - radius]
    total = (smap * m).sum(dim=(1, 2, 3)) / (m.sum(dim=(1, 2, 3)) * c)
    return total.to(gt.dtype)


def dssim(
    gt: torch.Tensor,
    est: torch.Tensor,
    data_range: float = 1.0,
    sigma: float = 1.5,
    mask: torch.Tensor | None = None,
    scale_invariant: bool = False,
) -> torch.Tensor:
    """Structural dissimilarity ``(1 − SSIM) / 2`` (see :func:`ssim`).

    Args:
        gt: linear ground truth ``(B, C, H, W)``.
        est: estimate, same shape.
        data_range: dynamic range ``L`` of the images (1 for [0, 1] data).
        sigma: Gaussian window std.
        mask: optional ``(B, 1, H, W)``; SSIM is averaged over masked valid pixels.
        scale_invariant: first scale ``est`` per channel by the least-squares ``α``
            (:func:`scale_to_match`), for methods whose output scale is arbitrary.

    Returns:
        ``(B,)`` in ``[0, 1]``, 0 for identical images.
    """
    if scale_invariant:
        est = scale_to_match(gt, est, mask)
    return (1.0 - ssim(gt, est, data_range, sigma, mask)) / 2.0
