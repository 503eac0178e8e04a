"""Local scale-invariant mean squared error (LMSE) of Grosse et al. 2009.

Grosse, Johnson, Adelson & Freeman, "Ground truth dataset and baseline evaluations for
intrinsic image algorithms", ICCV 2009, Section 4; the reference is ``local_error`` /
``score_image`` in their MIT intrinsic code. Choices made here:

- Windows are ``window × window`` with top-left corners ``0, shift, 2·shift, …`` as long as
  the window fits inside the image (no padding; a strip narrower than the shift at the
  right/bottom border is never covered, exactly as the reference). The mask acts inside
  each window: only masked pixels enter the sums, and fully unmasked windows add nothing.
- Per window and channel the estimate is scaled by ``α = Σ m·gt·est / Σ m·est²``; when
  ``Σ m·est² = 0`` the reference uses ``α = 0`` (it tests ``> 1e-5`` on its ×(65535/255)
  scale, i.e. ~1.5e-10 on [0, 1] data); here the test is ``> 0`` so the metric stays exactly
  invariant to the scale of both inputs.
- The normaliser is the ground-truth energy ``Σ m·gt²`` summed over the *same* windows
  (the corrected form of the reference, where this sum sits inside the window loop), so the
  score lies in ``[0, 1]``.
- Multi-channel inputs get one α per channel and window; numerator and normaliser are
  summed over channels. The MIT score uses one channel each: shading and gray (channel-mean)
  reflectance.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchiid.core.check import as_mask, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["local_mse", "mit_lmse"]


def _shape(x: object) -> object:
    return tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__


def _check_4d(x: torch.Tensor, name: str) -> None:
    """:func:`check_shape` ``(B, C, H, W)``, naming the one-image form too."""
    if isinstance(x, torch.Tensor) and x.dim() != 4:
        raise ShapeError(f"expected {name} of shape (B, C, H, W) or (C, H, W), got {_shape(x)}")
    check_shape(x, ("B", "C", "H", "W"), name)


def local_mse(
    gt: torch.Tensor,
    est: torch.Tensor,
    mask: torch.Tensor | None = None,
    window: int = 20,
    shift: int | None = None,
) -> torch.Tensor:
    """Local scale-invariant MSE (Grosse et al. 2009, ``local_error``).

    ``LMSE = Σ_w Σ_c Σ_{p∈w} m_p (gt_p − α_wc·est_p)² / Σ_w Σ_c Σ_{p∈w} m_p gt_p²`` with the
    per-window, per-channel least-squares scale ``α_wc = Σ m·gt·est / Σ m·est²`` (0 when the
    masked estimate is all zero). Computed in float64 with ``unfold``.

    Args:
        gt: ground truth, linear, ``(B, C, H, W)``, or one image ``(C, H, W)``.
        est: estimate, same shape (any global scale).
        mask: ``(B, 1, H, W)``, ``(1, 1, H, W)``, ``(B, H, W)`` or ``(H, W)`` (one image:
            ``(1, H, W)`` or ``(H, W)``); nonzero is inside; ``None`` for all pixels.
        window: window side (20 in Grosse et al.).
        shift: window stride (default ``window // 2``).

    Returns:
        ``(B,)`` LMSE per image (a 0-dim tensor for one ``(C, H, W)`` image), in the dtype
        of ``gt``; ``nan`` where the covered ground-truth energy is zero.

    Raises:
        ShapeError: ``gt`` is neither ``(B, C, H, W)`` nor ``(C, H, W)``, ``est`` has
            another shape, or the image is smaller than the window.

    Shape:
        - gt, est: ``(B, C, H, W)`` or ``(C, H, W)``; mask: ``(B, 1, H, W)``.
    """
    if isinstance(gt, torch.Tensor) and gt.dim() == 3:  # one image: a batch of one
        if not isinstance(est, torch.Tensor) or est.shape != gt.shape:
            raise ShapeError(f"est has shape {_shape(est)} but gt has shape {tuple(gt.shape)}")
        return local_mse(gt[None], est[None], mask, window, shift)[0]
    _check_4d(gt, "gt")
    if est.shape != gt.shape:
        raise ShapeError(f"est has shape {tuple(est.shape)} but gt has shape {tuple(gt.shape)}")
    shift = window // 2 if shift is None else shift
    if window < 1 or shift < 1:
        raise ParameterError(f"expected window >= 1 and shift >= 1, got {window}, {shift}")
    h, w = gt.shape[-2:]
    if h < window or w < window:
        raise ShapeError(f"image is {h}x{w}, smaller than the {window}x{window} LMSE window")
    m = as_mask(mask, gt).double()
    g = gt.double()
    e = est.to(g.device).double()
    b, c = g.shape[:2]

    def windows(x: torch.Tensor) -> torch.Tensor:
        # (B, C, H, W) -> (B, C, window*window, n_windows)
        cols = F.unfold(x.reshape(b * x.shape[1], 1, h, w), window, stride=shift)
        return cols.reshape(b, x.shape[1], window * window, -1)

    gw, ew, mw = windows(g), windows(e), windows(m)
    den = (mw * ew * ew).sum(dim=2, keepdim=True)
    num = (mw * gw * ew).sum(dim=2, keepdim=True)
    alpha = torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)
    err = (mw * (gw - alpha * ew) ** 2).sum(dim=(1, 2, 3))
    energy = (mw * gw * gw).sum(dim=(1, 2, 3))
    return (err / energy).to(gt.dtype)


def _gray(x: torch.Tensor) -> torch.Tensor:
    return x.mean(dim=1, keepdim=True) if x.shape[1] != 1 else x


def mit_lmse(
    true_reflectance: torch.Tensor,
    true_shading: torch.Tensor,
    est_reflectance: torch.Tensor,
    est_shading: torch.Tensor,
    mask: torch.Tensor | None = None,
    window: int = 20,
) -> torch.Tensor:
    """MIT intrinsic-images score ``½·LMSE(shading) + ½·LMSE(gray reflectance)``.

    Grosse et al. 2009 ``score_image``: windows ``window × window``, shift ``window // 2``.
    Reflectances with 3 channels are reduced to gray by the channel mean (the reference
    averages the ground truth and feeds gray estimates); a 3-channel shading (e.g. coloured
    illumination) is reduced the same way, a 1-channel one is used as is. All inputs linear.
    Arguments are reflectance first, as everywhere in the package.

    The four layers are either all batched ``(B, C, H, W)`` or all one image ``(C, H, W)``,
    the shape of a :class:`~torchiid.eval.datasets.MITDataset` sample's layers, so a sample
    scores directly: ``mit_lmse(s.reflectance, s.shading, est_r, est_s, s.mask)``.

    Args:
        true_reflectance: ``(B, 3, H, W)`` or ``(B, 1, H, W)``; one image: ``(3, H, W)`` or
            ``(1, H, W)``.
        true_shading: ``(B, 1, H, W)`` or ``(B, 3, H, W)``; one image: ``(1, H, W)`` or
            ``(3, H, W)``.
        est_reflectance: as ``true_reflectance``.
        est_shading: as ``true_shading``.
        mask: object mask, as in :func:`local_mse` (one image: ``(1, H, W)`` or ``(H, W)``).
        window: window side.

    Returns:
        ``(B,)`` scores (lower is better); a 0-dim tensor for one ``(C, H, W)`` image.

    Raises:
        ShapeError: the layers mix batched and one-image shapes, a layer has another
            channel count than 1 or 3, or the sizes differ.

    Example:
        >>> r, s = torch.rand(1, 3, 40, 40) + 0.1, torch.rand(1, 1, 40, 40) + 0.1
        >>> float(mit_lmse(r, s, 0.5 * r, 2 * s))  # scale-invariant
        0.0
        >>> float(mit_lmse(r[0], s[0], 0.5 * r[0], 2 * s[0]))  # one (C, H, W) image
        0.0
    """
    layers = {
        "true_reflectance": true_reflectance,
        "true_shading": true_shading,
        "est_reflectance": est_reflectance,
        "est_shading": est_shading,
    }
    dims = {x.dim() if isinstance(x, torch.Tensor) else None for x in layers.values()}
    if dims == {3}:  # one image each: a batch of one
        return mit_lmse(
            true_reflectance[None],
            true_shading[None],
            est_reflectance[None],
            est_shading[None],
            mask,
            window,
        )[0]
    if len(dims) > 1 and dims <= {3, 4}:
        shapes = ", ".join(f"{name} {tuple(x.shape)}" for name, x in layers.items())
        raise ShapeError(
            f"expected the four layers all batched (B, C, H, W) or all one image (C, H, W), "
            f"got {shapes}"
        )
    for name, x in layers.items():
        _check_4d(x, name)
        if x.shape[1] not in (1, 3):
            raise ShapeError(f"expected {name} with 1 or 3 channels, got {tuple(x.shape)}")
    s = local_mse(_gray(true_shading), _gray(est_shading), mask, window)
    r = local_mse(_gray(true_reflectance), _gray(est_reflectance), mask, window)
    return 0.5 * s + 0.5 * r
