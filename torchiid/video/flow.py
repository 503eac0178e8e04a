"""Optical flow between frames, its forward–backward occlusion check, and warping.

Conventions (those of Middlebury ``.flo`` files and of Sintel): a flow ``F_ab`` is a
``(B, 2, H, W)`` tensor ``(u, v)`` on the pixels of frame ``a``; pixel ``(x, y)`` of frame ``a``
shows the point seen at ``(x + u, y + v)`` in frame ``b``. :func:`warp` then brings frame ``b``
onto frame ``a`` (backward warping): ``warp(b, F_ab)(p) = b(p + F_ab(p))``, bilinear.

:func:`estimate_flow` uses OpenCV's DIS (Kroeger et al. 2016, preset ``medium``) or
Farnebäck's polynomial-expansion flow on the 8-bit sRGB luminance; :func:`occlusion_mask` is the
forward–backward check of Sundaram et al. (2010), with the constants Lai et al. (2018) use for
the warping error: a pixel of ``a`` is trusted when ``F_ab`` and ``F_ba`` (taken at the point it
moves to) cancel, ``|F_ab + F_ba'|² <= α (|F_ab|² + |F_ba'|²) + β`` (α = 0.01, β = 0.5 px²),
and it stays inside the frame.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["FLOW_METHODS", "estimate_flow", "warp", "occlusion_mask", "resize_flow"]

#: the flow estimators of :func:`estimate_flow`
FLOW_METHODS = ("dis", "farneback")


def _gray8(image: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` linear RGB -> ``(H, W)`` uint8 sRGB luminance."""
    x = image.detach().to("cpu", torch.float32)
    y = 0.2126 * x[0] + 0.7152 * x[1] + 0.0722 * x[2]
    # frames of any exposure: the flow needs contrast, not absolute values
    peak = float(torch.quantile(y.flatten()[:: max(1, y.numel() // 65536)], 0.99))
    if peak > 1:
        y = y / peak
    g = linear_to_srgb(y.clamp(0, 1)).mul_(255).round_()
    return np.ascontiguousarray(g.to(torch.uint8).numpy())


def estimate_flow(
    frame_a: torch.Tensor, frame_b: torch.Tensor, method: str = "dis"
) -> torch.Tensor:
    """Optical flow from ``frame_a`` to ``frame_b`` (see the module notes for the convention).

    Args:
        frame_a: ``(3, H, W)`` or ``(1, 3, H, W)`` linear RGB.
        frame_b: the same shape.
        method: ``"dis"`` (OpenCV's dense inverse search, preset medium; default) or
            ``"farneback"``.

    Returns:
        ``(1, 2, H, W)`` float32 flow on the CPU.

    Example:
        >>> a = torch.rand(3, 64, 80)
        >>> b = torch.roll(a, shifts=2, dims=2)  # content moves 2 px right
        >>> f = estimate_flow(a, b)
        >>> round(float(f[0, 0, 16:-16, 16:-16].median()))
        2
    """
    import cv2

    if method not in FLOW_METHODS:
        raise ParameterError(
            f"flow method must be one of {', '.join(FLOW_METHODS)}, got {method!r}"
        )
    a = frame_a[0] if frame_a.dim() == 4 else frame_a
    b = frame_b[0] if frame_b.dim() == 4 else frame_b
    if a.shape != b.shape or a.dim() != 3 or a.shape[0] != 3:
        raise ShapeError(f"flow needs two (3, H, W) frames, got {tuple(a.shape)}, {tuple(b.shape)}")
    ga, gb = _gray8(a), _gray8(b)
    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        flow = dis.calc(ga, gb, None)
    else:
        flow = cv2.calcOpticalFlowFarneback(ga, gb, None, 0.5, 4, 15, 3, 5, 1.2, 0)
    return torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1)))[None].float()


def _grid(flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sampling positions ``p + F(p)``: normalised grid, and absolute ``x``, ``y``."""
    _, _, h, w = flow.shape
    ys = torch.arange(h, dtype=flow.dtype, device=flow.device).view(1, h, 1)
    xs = torch.arange(w, dtype=flow.dtype, device=flow.device).view(1, 1, w)
    x = xs + flow[:, 0]
    y = ys + flow[:, 1]
    gx = 2 * x / max(w - 1, 1) - 1
    gy = 2 * y / max(h - 1, 1) - 1
    return torch.stack([gx, gy], dim=-1), x, y


def warp(
    image: torch.Tensor, flow: torch.Tensor, mode: str = "bilinear"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Backward warping: ``out(p) = image(p + flow(p))``.

    Args:
        image: ``(B, C, H, W)`` frame ``b`` (any values; a mask as float for ``"nearest"``).
        flow: ``(B, 2, H, W)`` flow from frame ``a`` to frame ``b``, on ``a``'s pixels.
        mode: ``"bilinear"``, ``"bicubic"`` (sharper; may overshoot) or ``"nearest"`` (for
            labels).

    Returns:
        ``(warped (B, C, H, W), inside (B, 1, H, W) bool)``: ``inside`` is False where
        ``p + flow(p)`` falls outside frame ``b`` (the warped value is then the border's).
    """
    if image.dim() != 4 or flow.dim() != 4 or flow.shape[1] != 2:
        raise ShapeError(
            f"warp needs (B, C, H, W) and (B, 2, H, W), got {tuple(image.shape)}, "
            f"{tuple(flow.shape)}"
        )
    if image.shape[0] != flow.shape[0] or image.shape[-2:] != flow.shape[-2:]:
        raise ShapeError(f"image {tuple(image.shape)} and flow {tuple(flow.shape)} differ")
    _, _, h, w = flow.shape
    flow = flow.to(device=image.device)
    work = image if image.is_floating_point() else image.to(torch.float32)
    grid, x, y = _grid(flow.to(work.dtype))
    out = F.grid_sample(work, grid, mode=mode, padding_mode="border", align_corners=True)
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return out.to(image.dtype), inside[:, None]


def occlusion_mask(
    forward: torch.Tensor, backward: torch.Tensor, alpha: float = 0.01, beta: float = 0.5
) -> torch.Tensor:
    """Pixels of frame ``a`` whose motion to ``b`` is trusted (forward–backward check).

    Args:
        forward: ``(B, 2, H, W)`` flow ``F_ab`` on ``a``'s pixels.
        backward: ``(B, 2, H, W)`` flow ``F_ba`` on ``b``'s pixels.
        alpha: relative tolerance (Sundaram et al. 2010; Lai et al. 2018: 0.01).
        beta: absolute tolerance in px² (0.5).

    Returns:
        ``(B, 1, H, W)`` bool: True where ``|F_ab + F_ba(p + F_ab)|² <= α (|F_ab|² +
        |F_ba(p + F_ab)|²) + β`` and ``p + F_ab(p)`` lies inside frame ``b``; False where the
        pixel is occluded in ``b``, leaves the frame, or the flow is unreliable.

    Example:
        >>> f = torch.zeros(1, 2, 8, 8); f[:, 0] = 2.0  # everything moves 2 px right
        >>> m = occlusion_mask(f, -f)
        >>> m[0, 0, 0].tolist()  # the last 2 columns leave the frame
        [True, True, True, True, True, True, False, False]
    """
    back_w, inside = warp(backward, forward)
    total = (forward + back_w).square().sum(1, keepdim=True)
    size = forward.square().sum(1, keepdim=True) + back_w.square().sum(1, keepdim=True)
    return (total <= alpha * size + beta) & inside


def resize_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """A flow field brought to another resolution ``(H, W)``, its vectors rescaled."""
    h0, w0 = flow.shape[-2:]
    if (h0, w0) == tuple(size):
        return flow
    # pixel centres as for the area-averaged frames: x_big + 0.5 = s (x + 0.5)
    out = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    sx, sy = size[1] / w0, size[0] / h0
    return torch.stack([out[:, 0] * sx, out[:, 1] * sy], dim=1)
