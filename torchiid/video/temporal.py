"""Temporally consistent decomposition of a frame sequence (:class:`VideoDecomposer`).

Decomposed one by one, the frames of a video flicker: every frame's solve lands somewhere
slightly different, and every frame's albedo scale (a quantile, see
:func:`~torchiid.model.full_resolution_layers`) moves with what is in view. The video loop ties
each frame ``t`` to the previous one, at the working resolution:

1. **Flow.** Optical flow ``F_{t→t−1}`` and ``F_{t−1→t}`` (OpenCV DIS, on the frames at up to
   ``flow_max_side`` px), and the pixels of frame ``t`` whose motion passes the
   forward–backward check (:func:`~torchiid.video.flow.occlusion_mask`) and that are inside
   both frames' masks: the *trusted* pixels.
2. **Target.** The previous reflectance warped onto frame ``t``: ``T = warp(R_{t−1}, F_{t→t−1})``.
3. **Warm start** of both stages (``decompose(..., init=)``): the shading PCG from
   ``log S0 = median(log(Σ I / Σ T))`` (3×3 median; continued smoothly where the warp is not
   trusted) instead of the coarse-to-fine cascade, Split-Bregman from ``I / S0``; and only the
   last ``later_iterations`` alternations of the schedule (``decompose(..., schedule_start=)``).
4. **Temporal term** (``decompose(..., temporal=)``): Stage 2 pulls ``R`` toward ``T`` on the
   trusted pixels, an L2 anchor (default) or an L1 term inside Split-Bregman
   (:class:`~torchiid.stages.config.TemporalPrior`). The shading has no temporal term: it is
   free to follow moving lights (it is ``I / R``).
5. **Stage 0 reuse.** When the scene moved little (the 90th percentile of the flow's length is
   at most ``reuse_max_motion`` working-resolution px and at least ``reuse_min_trusted`` of the
   pixels inside both frames' masks, all pixels without masks, are trusted), the previous
   frame's Stage 0 features are warped along the flow (proposal features and similarities
   bilinearly, segments by nearest neighbour; the CNN patch descriptors kept) instead of
   recomputed, for at most ``reuse_max_frames`` frames in a row.
6. **One scale for the sequence.** The first frame's albedo scale holds for the whole
   sequence: every later frame's ``(R, S)`` is rescaled by the median of ``Σ_c T / Σ_c R`` over
   the trusted pixels, so the reflectance does not flicker with the per-frame quantile; pixels
   that would exceed 1 move their excess into the shading, as for a still image (R stays an
   albedo in [0, 1], ``R · S == I``). The viewable shading uses the first frame's
   ``shading_white`` throughout.

A frame without a usable predecessor (the first, one after :meth:`VideoDecomposer.reset`, a
frame of another size) is decomposed as a still image.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.semantic import SemanticFeatures
from torchiid.model import Decomposition, decompose
from torchiid.params import Parameters
from torchiid.resample import downsample, working_size
from torchiid.stages.config import TEMPORAL_NORMS, TemporalPrior
from torchiid.video.flow import FLOW_METHODS, estimate_flow, occlusion_mask, resize_flow, warp

__all__ = ["VideoOptions", "VideoFrame", "VideoDecomposer", "DEFAULT_TEMPORAL_WEIGHT"]

#: default weight of the temporal term per norm (relative to Stage 2's data term)
DEFAULT_TEMPORAL_WEIGHT = {"l2": 4.0, "l1": 1.0}


@dataclass(frozen=True)
class VideoOptions:
    """How frames are tied together (see the module notes).

    Attributes:
        temporal_norm: ``"l2"`` (anchor) or ``"l1"`` (Split-Bregman term).
        temporal_weight: weight of the temporal term relative to Stage 2's data term
            (``None``: :data:`DEFAULT_TEMPORAL_WEIGHT` of the norm; 0: no temporal term).
        warm_start: start both stages of frame ``t`` from the warped previous reflectance.
        init_median: side of the median filter applied to the warm start's log-shading
            ``log(Σ I / Σ T)`` (1 or 0: none). The warped reflectance's edges are a little
            blurred and shifted (resampling, flow error), so dividing the sharp new frame by it
            leaves thin ridges along every edge; solved from there with capped iterations,
            they would stay in the shading and accumulate frame after frame. A 3×3 median
            removes ridges of a pixel or two and keeps the shading's own edges.
        target_sigma: ``> 0``: the temporal target keeps only the warped reflectance's levels,
            smoothed over this many working-resolution px, and the current ``ρ``'s detail
            (:class:`~torchiid.stages.config.TemporalPrior` ``sigma``); 0 (default): the
            warped reflectance as it is.
        later_iterations: alternations of a warm-started frame: the last ``later_iterations``
            of the §3.4 schedule (``decompose(..., schedule_start=)``); 0: all
            ``params.iterations``.
        match_scale: one albedo scale for the sequence (else each frame's own quantile).
        reuse_features: warp the previous frame's Stage 0 features when the scene moved little.
        reuse_max_motion: 90th percentile of the flow's length (working-resolution px) up to
            which features are reused.
        reuse_min_trusted: share of trusted pixels (of those inside both frames' masks)
            needed to reuse features.
        reuse_max_frames: features are recomputed at least every ``reuse_max_frames + 1``
            frames.
        flow: ``"dis"`` or ``"farneback"`` (:func:`~torchiid.video.flow.estimate_flow`).
        flow_max_side: the flow is estimated on the frames brought to this longer side
            (0: full resolution), then resized to the working resolution; finer than the
            working resolution because the flow's error, not its cost, limits the temporal
            term (on Sintel 1024 px flows have about 0.6× the end-point error of 512 px ones).
        occlusion_alpha: relative tolerance of the forward–backward check.
        occlusion_beta: absolute tolerance (px² at the flow's resolution).
    """

    temporal_norm: str = "l2"
    temporal_weight: float | None = None
    warm_start: bool = True
    later_iterations: int = 2
    init_median: int = 3
    target_sigma: float = 0.0
    match_scale: bool = True
    reuse_features: bool = True
    reuse_max_motion: float = 4.0
    reuse_min_trusted: float = 0.8
    reuse_max_frames: int = 4
    flow: str = "dis"
    flow_max_side: int = 1024
    occlusion_alpha: float = 0.01
    occlusion_beta: float = 0.5

    def __post_init__(self) -> None:
        if self.temporal_norm not in TEMPORAL_NORMS:
            raise ParameterError(
                f"temporal norm must be one of {', '.join(TEMPORAL_NORMS)}, "
                f"got {self.temporal_norm!r}"
            )
        if self.temporal_weight is not None and not self.temporal_weight >= 0:
            raise ParameterError(f"temporal weight must be >= 0, got {self.temporal_weight}")
        if self.flow not in FLOW_METHODS:
            raise ParameterError(
                f"flow method must be one of {', '.join(FLOW_METHODS)}, got {self.flow!r}"
            )
        if self.init_median < 0 or self.init_median > 1 and self.init_median % 2 == 0:
            raise ParameterError(f"init_median must be 0, 1 or odd, got {self.init_median}")
        if not self.target_sigma >= 0:
            raise ParameterError(f"target_sigma must be >= 0, got {self.target_sigma}")
        if self.later_iterations < 0:
            raise ParameterError(f"later_iterations must be >= 0, got {self.later_iterations}")
        if self.reuse_max_frames < 0 or not self.reuse_max_motion >= 0:
            raise ParameterError("reuse_max_frames and reuse_max_motion must be >= 0")

    @property
    def weight(self) -> float:
        """The temporal weight in use."""
        if self.temporal_weight is None:
            return DEFAULT_TEMPORAL_WEIGHT[self.temporal_norm]
        return float(self.temporal_weight)

    @property
    def linked(self) -> bool:
        """Whether frames are tied at all (else every frame is a still decomposition)."""
        return self.weight > 0 or self.warm_start or self.match_scale or self.reuse_features

    @classmethod
    def frame_by_frame(cls) -> VideoOptions:
        """Every frame decomposed on its own, exactly as ``decompose`` does (the baseline)."""
        return cls(temporal_weight=0.0, warm_start=False, match_scale=False, reuse_features=False)

    def replace(self, **changes: object) -> VideoOptions:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class VideoFrame:
    """One decomposed frame.

    Attributes:
        index: 0-based position in the sequence (counting every frame given).
        decomposition: the :class:`~torchiid.model.Decomposition`, with ``reflectance``,
            ``shading`` and ``shading_white`` in the sequence's convention (module notes, 6).
        linked: whether the frame was tied to its predecessor (False: a still decomposition).
        trusted: share of the working-resolution pixels whose warp was trusted, among the
            pixels inside both frames' masks (the mask of this frame and the previous frame's
            mask warped onto it; all pixels without masks); 0 unlinked.
        motion: 90th percentile of the flow's length, working-resolution px (0 unlinked).
        features_reused: Stage 0 came from the previous frame, warped.
        scale: the factor applied to the reflectance to keep the sequence's scale (1: none).
        times: seconds: ``"flow"``, ``"features"`` (Stage 0 or its warp), ``"decompose"``
            (the method itself, Stage 0 excluded), ``"total"``.
    """

    index: int
    decomposition: Decomposition
    linked: bool = False
    trusted: float = 0.0
    motion: float = 0.0
    features_reused: bool = False
    scale: float = 1.0
    times: dict[str, float] = field(default_factory=dict)

    @property
    def reflectance(self) -> torch.Tensor:
        """``(1, 3, H, W)`` linear reflectance."""
        return self.decomposition.reflectance

    @property
    def shading(self) -> torch.Tensor:
        """``(1, 1, H, W)`` linear gray shading."""
        return self.decomposition.shading


@dataclass
class _Previous:
    size: tuple[int, int]
    image: torch.Tensor  # (1, 3, hf, wf) flow resolution
    reflectance: torch.Tensor  # (1, 3, h, w) working resolution
    mask: torch.Tensor | None  # (1, 1, h, w) bool
    features: SemanticFeatures | None
    reused: int


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


def _warp_features(feats: SemanticFeatures, flow: torch.Tensor) -> SemanticFeatures:
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


def _keep_albedo(
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


class VideoDecomposer:
    """Decompose the frames of a sequence one after another, each tied to the previous one.

    Args:
        params: the method's :class:`~torchiid.params.Parameters` (default: ``Parameters()``).
        options: :class:`VideoOptions` (default: L2 temporal term, warm start, feature reuse,
            one scale).
        return_stage1: also return each frame's Stage 1 layers at full resolution.

    Example:
        >>> from torchiid.synthetic import moving_mondrian
        >>> seq = moving_mondrian(64, 80, frames=2)
        >>> p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
        >>> video = VideoDecomposer(p)
        >>> frames = [video(img) for img in seq.images]
        >>> frames[1].linked, frames[1].reflectance.shape
        (True, torch.Size([1, 3, 64, 80]))
    """

    def __init__(
        self,
        params: Parameters | None = None,
        options: VideoOptions | None = None,
        *,
        return_stage1: bool = False,
    ) -> None:
        self.params = params if params is not None else Parameters()
        self.options = options if options is not None else VideoOptions()
        self.return_stage1 = return_stage1
        self.shading_white: torch.Tensor | None = None
        self._prev: _Previous | None = None
        self._count = 0

    def reset(self) -> None:
        """Forget the previous frame (a cut): the next frame is decomposed as a still image."""
        self._prev = None
        self.shading_white = None

    def _working(self, image: torch.Tensor) -> tuple[int, int]:
        return working_size(image.shape[-2], image.shape[-1], self.params.output.max_side)

    def _flow_size(self, image: torch.Tensor) -> tuple[int, int]:
        return working_size(image.shape[-2], image.shape[-1], self.options.flow_max_side)

    def remember(
        self,
        image: torch.Tensor,
        reflectance: torch.Tensor,
        mask: torch.Tensor | None = None,
        shading_white: float | None = None,
    ) -> None:
        """Take a frame decomposed earlier (e.g. read back from files) as the previous one.

        Args:
            image: ``(3, H, W)`` or ``(1, 3, H, W)`` linear frame.
            reflectance: its reflectance, same shape.
            mask: its mask ``(1, H, W)`` / ``(1, 1, H, W)`` or ``None``.
            shading_white: the sequence's ``shading_white`` if not known yet.
        """
        image = image[None] if image.dim() == 3 else image
        reflectance = reflectance[None] if reflectance.dim() == 3 else reflectance
        if mask is not None:
            mask = mask[None] if mask.dim() == 3 else mask
        if reflectance.shape != image.shape:
            raise ShapeError(
                f"reflectance {tuple(reflectance.shape)} and image {tuple(image.shape)} differ"
            )
        size = self._working(image)
        msk = None if mask is None else downsample(mask.to(image.dtype), size) > 0.5
        self._prev = _Previous(
            size=tuple(image.shape[-2:]),
            image=downsample(image.float(), self._flow_size(image)),
            reflectance=downsample(reflectance.to(image.dtype), size),
            mask=msk,
            features=None,
            reused=0,
        )
        if self.shading_white is None and shading_white is not None:
            self.shading_white = torch.tensor([float(shading_white)])
        self._count += 1

    @torch.no_grad()
    def __call__(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> VideoFrame:
        """Decompose the next frame.

        Args:
            image: ``(3, H, W)`` or ``(1, 3, H, W)`` linear RGB (any device).
            mask: optional ``(1, H, W)`` / ``(1, 1, H, W)`` mask, nonzero inside.

        Returns:
            :class:`VideoFrame`.
        """
        t_start = time.perf_counter()
        o, p = self.options, self.params
        if not isinstance(image, torch.Tensor):
            raise ShapeError(f"expected a frame tensor, got {type(image).__name__}")
        image = image[None] if image.dim() == 3 else image
        if image.dim() != 4 or image.shape[0] != 1:
            raise ShapeError(f"expected one frame (3, H, W), got {tuple(image.shape)}")
        if mask is not None:
            mask = torch.as_tensor(mask)
            mask = (mask[None] if mask.dim() == 3 else mask).to(image.device) != 0
        size = self._working(image)
        img_lo = downsample(image.float(), size)
        img_flow = downsample(image.float(), self._flow_size(image))
        msk_lo = None if mask is None else downsample(mask.to(img_lo.dtype), size) > 0.5
        prev = self._prev
        linked = o.linked and prev is not None and prev.size == tuple(image.shape[-2:])
        index = self._count
        self._count += 1
        times: dict[str, float] = {}
        trusted_share = motion = 0.0
        init = temporal = feats = None
        reused = False
        target = trusted = None
        if linked:
            t0 = time.perf_counter()
            fw = estimate_flow(img_flow[0].cpu(), prev.image[0].cpu(), o.flow)
            bw = estimate_flow(prev.image[0].cpu(), img_flow[0].cpu(), o.flow)
            trusted = occlusion_mask(fw, bw, o.occlusion_alpha, o.occlusion_beta)
            if tuple(fw.shape[-2:]) != size:
                fw = resize_flow(fw, size)
                trusted = downsample(trusted.float(), size) > 0.5
            fw, trusted = fw.to(img_lo.device), trusted.to(img_lo.device)
            region = torch.ones_like(trusted)  # inside both frames' masks
            if msk_lo is not None:
                region &= msk_lo
            if prev.mask is not None:
                region &= warp(prev.mask.to(img_lo.dtype), fw, mode="nearest")[0] > 0.5
            trusted &= region
            target = warp(prev.reflectance, fw)[0].clamp_min(0)
            # a share of the masked area, not of the frame: else a mask covering less than
            # reuse_min_trusted of the frame would never let Stage 0 be reused
            area = int(region.sum())
            trusted_share = float(trusted.sum()) / area if area else 0.0
            length = fw.square().sum(1).sqrt().flatten()
            motion = float(torch.quantile(length[:: max(1, length.numel() // 65536)], 0.9))
            times["flow"] = time.perf_counter() - t0
            if o.warm_start:
                init = self._warm_start(img_lo, target, trusted)
            if o.weight > 0:
                temporal = TemporalPrior(
                    target,
                    trusted.to(img_lo.dtype),
                    o.weight,
                    o.temporal_norm,
                    sigma=o.target_sigma,
                )
            t0 = time.perf_counter()
            if (
                o.reuse_features
                and prev.features is not None
                and prev.reused < o.reuse_max_frames
                and motion <= o.reuse_max_motion
                and trusted_share >= o.reuse_min_trusted
            ):
                feats = _warp_features(prev.features, fw)
                reused = True
            times["features"] = time.perf_counter() - t0
        start = 1
        if init is not None and 0 < o.later_iterations < p.iterations:
            start = p.iterations - o.later_iterations + 1
        t0 = time.perf_counter()
        result = decompose(
            image,
            p,
            mask=mask,
            features=feats,
            init=init,
            temporal=temporal,
            return_stage1=self.return_stage1,
            return_features=o.reuse_features,
            schedule_start=start,
        )
        t1 = time.perf_counter()
        if not reused:
            stage0 = sum(
                v
                for k, v in result.times.items()
                if not (k.startswith("shading ") or k.startswith("reflectance ") or k == "total")
            )
            times["features"] = times.get("features", 0.0) + stage0
        times["decompose"] = t1 - t0 - (0.0 if reused else times["features"])
        scale = 1.0
        refl, shading, excess = result.reflectance, result.shading, result.albedo_excess
        if linked and o.match_scale and target is not None:
            r_lo = downsample(refl.float(), size)
            t_sum, r_sum = target.sum(1, keepdim=True), r_lo.sum(1, keepdim=True)
            ok = trusted & (t_sum > 1e-3) & (r_sum > 1e-3)
            if bool(ok.any()):
                scale = float((t_sum[ok] / r_sum[ok]).median())
                refl, shading, over = _keep_albedo(refl, shading, scale, mask)
                if scale >= 1:  # else the pixels moved before stay the ones counted
                    excess = over.to(excess.device)
        white = result.shading_white
        if o.match_scale:
            if not linked or self.shading_white is None:
                self.shading_white = result.shading_white.detach().cpu()
            white = self.shading_white.to(result.shading_white)
        decomposition = dataclasses.replace(
            result, reflectance=refl, shading=shading, shading_white=white, albedo_excess=excess
        )
        self._prev = _Previous(
            size=tuple(image.shape[-2:]),
            image=img_flow,
            reflectance=downsample(refl.float(), size),
            mask=msk_lo,
            features=result.features if o.reuse_features else None,
            reused=prev.reused + 1 if reused and prev is not None else 0,
        )
        times["total"] = time.perf_counter() - t_start
        return VideoFrame(
            index=index,
            decomposition=decomposition,
            linked=linked,
            trusted=trusted_share,
            motion=motion,
            features_reused=reused,
            scale=scale,
            times=times,
        )

    def _warm_start(
        self, img: torch.Tensor, target: torch.Tensor, trusted: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(R0, S0)`` at the working resolution from the warped previous reflectance."""
        floor = self.params.reflectance.shading_floor
        s_est = img.sum(1, keepdim=True) / target.sum(1, keepdim=True).clamp_min(floor)
        known = trusted & (target.sum(1, keepdim=True) > 1e-3) & (img.sum(1, keepdim=True) > 0)
        if not bool(known.any()):
            s0 = _blur(img.mean(1, keepdim=True), max(min(img.shape[-2:]) / 16, 1.0))
            s0 = s0.clamp_min(floor)
        else:
            log_s = _fill(s_est.clamp_min(floor).log(), known)
            if self.options.init_median > 1:  # no ridges along the warp's shifted edges
                log_s = _median(log_s, self.options.init_median)
            s0 = log_s.exp()
        if self.options.init_median > 1:
            return img / s0, s0
        r0 = torch.where(known, target, img / s0)
        return r0, s0
