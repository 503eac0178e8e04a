"""Tying a frame to its predecessor: flow and trust, warm start, feature warp, one scale.

The steps of :class:`~torchiid.video.temporal.VideoDecomposer` (see its module notes), each a
function of the two frames at the working resolution:

* :func:`link_frames` — flow both ways, the trusted pixels, the warped previous reflectance
  (the target) and the motion;
* :func:`warm_start` — ``(R0, S0)`` for both stages from the target;
* :func:`warp_features` — the previous frame's Stage 0 features carried along the flow;
* :func:`match_scale` — the frame's ``(R, S)`` brought to the sequence's albedo scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from torchiid.features.semantic import SemanticFeatures
from torchiid.model import Decomposition
from torchiid.resample import downsample
from torchiid.video.flow import estimate_flow, occlusion_mask, resize_flow, warp
from torchiid.video.options import VideoOptions

__all__ = [
    "Link",
    "Previous",
    "keep_albedo",
    "link_frames",
    "match_scale",
    "warm_start",
    "warp_features",
]


@dataclass
class Previous:
    """What the next frame needs of the previous one."""

    size: tuple[int, int]  # full resolution
    image: torch.Tensor  # (1, 3, hf, wf) flow resolution
    reflectance: torch.Tensor  # (1, 3, h, w) working resolution
    mask: torch.Tensor | None  # (1, 1, h, w) bool
    features: SemanticFeatures | None
    reused: int  # frames in a row whose Stage 0 came from a warp


@dataclass(frozen=True)
class Link:
    """How frame ``t`` relates to frame ``t − 1`` at the working resolution.

    Attributes:
        flow: ``(1, 2, h, w)`` flow ``F_{t→t−1}``.
        trusted: ``(1, 1, h, w)`` bool: the warp passes the forward–backward check and the
            pixel is inside both frames' masks.
        target: ``(1, 3, h, w)`` the previous reflectance warped onto frame ``t``.
        trusted_share: share of the trusted pixels among those inside both frames' masks.
        motion: 90th percentile of the flow's length (px).
    """

    flow: torch.Tensor
    trusted: torch.Tensor
    target: torch.Tensor
    trusted_share: float
    motion: float


def link_frames(
    prev: Previous,
    img_flow: torch.Tensor,
    mask: torch.Tensor | None,
    like: torch.Tensor,
    options: VideoOptions,
) -> Link:
    """The :class:`Link` of a frame to the previous one.

    Args:
        prev: the previous frame.
        img_flow: ``(1, 3, hf, wf)`` the frame at the flow's resolution.
        mask: ``(1, 1, h, w)`` bool mask of the frame at the working resolution, or ``None``.
        like: the frame at the working resolution ``(h, w)``: the device and dtype of the link.
        options: the flow method and the forward–backward tolerances.
    """
    o, size = options, tuple(like.shape[-2:])
    fw = estimate_flow(img_flow[0].cpu(), prev.image[0].cpu(), o.flow)
    bw = estimate_flow(prev.image[0].cpu(), img_flow[0].cpu(), o.flow)
    trusted = occlusion_mask(fw, bw, o.occlusion_alpha, o.occlusion_beta)
    if tuple(fw.shape[-2:]) != size:
        fw = resize_flow(fw, size)
        trusted = downsample(trusted.float(), size) > 0.5
    fw, trusted = fw.to(like.device), trusted.to(like.device)
    region = torch.ones_like(trusted)  # inside both frames' masks
    if mask is not None:
        region &= mask
    if prev.mask is not None:
        region &= warp(prev.mask.to(like.dtype), fw, mode="nearest")[0] > 0.5
    trusted &= region
    target = warp(prev.reflectance, fw)[0].clamp_min(0)
    # a share of the masked area, not of the frame: else a mask covering less than
    # reuse_min_trusted of the frame would never let Stage 0 be reused
    area = int(region.sum())
    share = float(trusted.sum()) / area if area else 0.0
    length = fw.square().sum(1).sqrt().flatten()
    motion = float(torch.quantile(length[:: max(1, length.numel() // 65536)], 0.9))
    return Link(fw, trusted, target, share, motion)


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)`` with reflect padding (radius 3σ)."""
    r = max(1, min(int(3 * sigma), min(x.shape[-2:]) - 1))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-(t * t) / (2 * sigma * sigma))
    k = k / k.sum()
    c = x.shape[1]
    x = F.pad(x, (r, r, 0, 0), mode="reflect")
    x = F.conv2d(x, k.view(1, 1, 1, -1).expand(c, 1, 1, -1).contiguous(), groups=c)
    x = F.pad(x, (0, 0, r, r), mode="reflect")
    return F.conv2d(x, k.view(1, 1, -1, 1).expand(c, 1, -1, 1).contiguous(), groups=c)


def _fill(values: torch.Tensor, known: torch.Tensor) -> torch.Tensor:
    """``values`` where ``known``, a smooth continuation elsewhere (normalised convolution)."""
    w = known.to(values.dtype)
    out = values.clone()
    missing = ~known
    side = min(values.shape[-2:])
    for sigma in (side / 64, side / 16, side / 4):
        num, den = _blur(values * w, max(sigma, 1.0)), _blur(w, max(sigma, 1.0))
        ok = den > 1e-3
        fill = missing & ok
        out = torch.where(fill, num / den.clamp_min(1e-12), out)
        missing = missing & ~ok
        if not bool(missing.any()):
            return out
    mean = (values * w).sum() / w.sum().clamp_min(1e-12)
    return torch.where(missing, mean, out)


def warp_features(feats: SemanticFeatures, flow: torch.Tensor) -> SemanticFeatures:
    """Stage 0 features of the previous frame carried along the flow onto this frame."""
    fl = flow.to(device=feats.gpca.device if feats.gpca is not None else flow.device)

    def bilinear(x: torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None else warp(x, fl.to(x.device, x.dtype))[0].contiguous()

    segs = None
    if feats.segments is not None:
        lab = feats.segments[:, None].to(torch.float64)
        segs = warp(lab, fl.to(lab.device, lab.dtype), mode="nearest")[0][:, 0]
        segs = segs.round().to(feats.segments.dtype).contiguous()
    return SemanticFeatures(
        patch_centers=feats.patch_centers,
        patch_features=feats.patch_features,
        similarity=bilinear(feats.similarity),
        gpca=bilinear(feats.gpca),
        segments=segs,
        midlevel=None,
        times={},
    )


def _median(x: torch.Tensor, size: int) -> torch.Tensor:
    """``size × size`` median filter of ``(B, C, H, W)`` (replicate padding)."""
    r = size // 2
    padded = F.pad(x, (r, r, r, r), mode="replicate")
    patches = padded.unfold(2, size, 1).unfold(3, size, 1)
    return patches.reshape(*x.shape, size * size).median(dim=-1).values


def keep_albedo(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    factor: float,
    mask: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(c·R, S / c)`` with the pixels above 1 moving their excess into the shading.

    Returns:
        the reflectance, the shading, and the ``(1,)`` share of the pixels (inside the mask)
        above 1 after the scale.
    """
    r = reflectance * factor
    s = shading / factor
    peak = r.amax(1, keepdim=True)
    over = peak > 1
    excess = peak.clamp_min(1)
    r, s = (r / excess).clamp_(0, 1), s * excess
    if mask is not None:
        over &= mask
        r, s = r * mask, s * mask
        area = mask.flatten(1).sum(1).clamp_min(1)
    else:
        area = torch.full((r.shape[0],), float(over[0, 0].numel()), device=r.device)
    return r, s, (over.flatten(1).sum(1) / area).to(torch.float32)


def warm_start(
    img: torch.Tensor, link: Link, floor: float, init_median: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R0, S0)`` at the working resolution from the warped previous reflectance.

    Args:
        img: ``(1, 3, h, w)`` the frame at the working resolution.
        link: the frame's :class:`Link`.
        floor: the smallest shading (``params.reflectance.shading_floor``).
        init_median: side of the median filter of the log-shading
            (:attr:`~torchiid.video.options.VideoOptions.init_median`).
    """
    target, trusted = link.target, link.trusted
    s_est = img.sum(1, keepdim=True) / target.sum(1, keepdim=True).clamp_min(floor)
    known = trusted & (target.sum(1, keepdim=True) > 1e-3) & (img.sum(1, keepdim=True) > 0)
    if not bool(known.any()):
        s0 = _blur(img.mean(1, keepdim=True), max(min(img.shape[-2:]) / 16, 1.0))
        s0 = s0.clamp_min(floor)
    else:
        log_s = _fill(s_est.clamp_min(floor).log(), known)
        if init_median > 1:  # no ridges along the warp's shifted edges
            log_s = _median(log_s, init_median)
        s0 = log_s.exp()
    if init_median > 1:
        return img / s0, s0
    r0 = torch.where(known, target, img / s0)
    return r0, s0


def match_scale(
    result: Decomposition, link: Link, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """The frame's reflectance, shading and albedo excess at the sequence's scale, and the factor.

    The factor is the median of ``Σ_c T / Σ_c R`` over the trusted pixels (``T`` the warped
    previous reflectance); 1, and the layers unchanged, when no pixel qualifies.
    """
    refl, shading, excess = result.reflectance, result.shading, result.albedo_excess
    r_lo = downsample(refl.float(), tuple(link.target.shape[-2:]))
    t_sum, r_sum = link.target.sum(1, keepdim=True), r_lo.sum(1, keepdim=True)
    ok = link.trusted & (t_sum > 1e-3) & (r_sum > 1e-3)
    if not bool(ok.any()):
        return refl, shading, excess, 1.0
    scale = float((t_sum[ok] / r_sum[ok]).median())
    refl, shading, over = keep_albedo(refl, shading, scale, mask)
    if scale >= 1:  # below 1 no pixel newly exceeds 1: the decomposition's count stands
        excess = over.to(excess.device)
    return refl, shading, excess, scale
