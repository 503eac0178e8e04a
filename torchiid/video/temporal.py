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

from torchiid.core.exceptions import ShapeError
from torchiid.model import Decomposition, decompose
from torchiid.params import Parameters
from torchiid.resample import downsample, working_size
from torchiid.stages.config import TemporalPrior
from torchiid.video.linking import (
    Link,
    Previous,
    link_frames,
    match_scale,
    warm_start,
    warp_features,
)
from torchiid.video.options import DEFAULT_TEMPORAL_WEIGHT as DEFAULT_TEMPORAL_WEIGHT
from torchiid.video.options import VideoOptions as VideoOptions

__all__ = ["VideoFrame", "VideoDecomposer"]


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
        self._prev: Previous | None = None
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
        self._prev = Previous(
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
        image, mask = _one_frame(image, mask)
        size = self._working(image)
        img_lo = downsample(image.float(), size)
        img_flow = downsample(image.float(), self._flow_size(image))
        msk_lo = None if mask is None else downsample(mask.to(img_lo.dtype), size) > 0.5
        prev = self._prev
        linked = o.linked and prev is not None and prev.size == tuple(image.shape[-2:])
        index = self._count
        self._count += 1
        times: dict[str, float] = {}
        link = init = temporal = feats = None
        if linked:
            t0 = time.perf_counter()
            link = link_frames(prev, img_flow, msk_lo, img_lo, o)
            times["flow"] = time.perf_counter() - t0
            if o.warm_start:
                init = warm_start(img_lo, link, p.reflectance.shading_floor, o.init_median)
            if o.weight > 0:
                trusted = link.trusted.to(img_lo.dtype)
                temporal = TemporalPrior(
                    link.target, trusted, o.weight, o.temporal_norm, sigma=o.target_sigma
                )
            t0 = time.perf_counter()
            if self._reuse(prev, link):
                feats = warp_features(prev.features, link.flow)
            times["features"] = time.perf_counter() - t0
        reused = feats is not None
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
            times["features"] = times.get("features", 0.0) + _stage0_seconds(result.times)
        times["decompose"] = t1 - t0 - (0.0 if reused else times["features"])
        decomposition, scale = self._in_sequence_scale(result, link, mask)
        self._prev = Previous(
            size=tuple(image.shape[-2:]),
            image=img_flow,
            reflectance=downsample(decomposition.reflectance.float(), size),
            mask=msk_lo,
            features=result.features if o.reuse_features else None,
            reused=prev.reused + 1 if reused and prev is not None else 0,
        )
        times["total"] = time.perf_counter() - t_start
        return VideoFrame(
            index,
            decomposition,
            linked=linked,
            trusted=link.trusted_share if link is not None else 0.0,
            motion=link.motion if link is not None else 0.0,
            features_reused=reused,
            scale=scale,
            times=times,
        )

    def _reuse(self, prev: Previous, link: Link) -> bool:
        """Whether the previous frame's Stage 0 features serve, warped (the scene moved little)."""
        o = self.options
        return (
            o.reuse_features
            and prev.features is not None
            and prev.reused < o.reuse_max_frames
            and link.motion <= o.reuse_max_motion
            and link.trusted_share >= o.reuse_min_trusted
        )

    def _in_sequence_scale(
        self, result: Decomposition, link: Link | None, mask: torch.Tensor | None
    ) -> tuple[Decomposition, float]:
        """``result`` in the sequence's convention (module notes, 6) and the scale applied."""
        scale = 1.0
        refl, shading, excess = result.reflectance, result.shading, result.albedo_excess
        if link is not None and self.options.match_scale:
            refl, shading, excess, scale = match_scale(result, link, mask)
        white = result.shading_white
        if self.options.match_scale:
            if link is None or self.shading_white is None:
                self.shading_white = result.shading_white.detach().cpu()
            white = self.shading_white.to(result.shading_white)
        decomposition = dataclasses.replace(
            result, reflectance=refl, shading=shading, shading_white=white, albedo_excess=excess
        )
        return decomposition, scale


def _one_frame(
    image: torch.Tensor, mask: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(1, 3, H, W)`` frame and ``(1, 1, H, W)`` bool mask (or ``None``), checked."""
    if not isinstance(image, torch.Tensor):
        raise ShapeError(f"expected a frame tensor, got {type(image).__name__}")
    image = image[None] if image.dim() == 3 else image
    if image.dim() != 4 or image.shape[0] != 1:
        raise ShapeError(f"expected one frame (3, H, W), got {tuple(image.shape)}")
    if mask is not None:
        mask = torch.as_tensor(mask)
        mask = (mask[None] if mask.dim() == 3 else mask).to(image.device) != 0
    return image, mask


def _stage0_seconds(times: dict[str, float]) -> float:
    """Stage 0's seconds among a decomposition's times (not the steps, marks and total)."""
    return sum(
        v
        for k, v in times.items()
        if not (
            k.startswith(("shading ", "reflectance "))
            or k in ("total", "coarse inputs", "texture marks")
        )
    )
