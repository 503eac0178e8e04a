"""Coarse-to-fine alternations: all but the last at a fraction of the working resolution.

The §3.4 schedule's alternations refine one answer: each starts from the previous shading
(the shading PCG's warm start) and reflectance (the next matting base and the Split-Bregman
start). With ``params.coarse_scale`` below 1 the alternations ``1 .. k − 1`` run on the image
brought to that fraction of the working resolution's sides, and their shading, brought back
up, starts the shading solve of alternation ``k`` at the working resolution, whose Stage 2
starts from its ``ρ`` as a first alternation's does. Every
alternation solves the paper's terms with the §3.4 weights; at the coarse size the terms
counted per patch (``S_c``) and per segment (``C``) weigh about four times more against the
per-pixel ones, whose pixels are a quarter as many at half size.

Stage 0 runs once, at the working resolution: the coarse alternations take its features
resampled (:func:`coarse_features`), so the CNN and the proposals are not run twice.

It applies to a cold decomposition with a shading stage only: a warm start (``init``), a
temporal prior or a ``schedule_start`` after 1 already says where the solves start, without
Stage 1 there is no shading solve to start, and a coarse size whose shorter side falls below
the patch size runs every alternation at the working resolution.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import torch
import torch.nn.functional as F

from torchiid.features.midlevel import MidLevelBatch, MidLevelFeatures
from torchiid.features.semantic import SemanticFeatures, pca_features
from torchiid.params import Parameters
from torchiid.pipeline.alternation import Alternation
from torchiid.pipeline.inputs import WorkingInputs, downsampled
from torchiid.pipeline.layers import final_shading, log_luminance
from torchiid.pipeline.results import IterationLayers
from torchiid.priors.shading_terms import shading_stencil
from torchiid.resample import GuidedUpsampler, downsample

__all__ = ["coarse_size", "coarse_features", "coarse_alternations", "hand_over"]

#: called after each alternation ``k`` of the coarse run, with the run
Done = Callable[[int, Alternation], None]


def coarse_size(work: WorkingInputs, params: Parameters) -> tuple[int, int] | None:
    """The size the alternations before the last run at, or ``None`` for the working size.

    ``None`` when ``params.coarse_scale`` is 1, for a single alternation, without a shading
    stage (whose solve the coarse run starts), for a warm start, a temporal prior or a later
    ``schedule_start``, and when the coarse image's shorter side would be below
    ``params.features.patch_size``.
    """
    scale = params.coarse_scale
    if scale >= 1 or params.iterations < 2 or work.first != 1:
        return None
    if not params.alternation(params.iterations)[0].active:
        return None  # no shading solve to start (baselines 2 and 3): nothing to hand over
    if work.log_shading0 is not None or work.reflectance0 is not None or work.temporal is not None:
        return None
    h, w = work.size
    size = (max(1, round(h * scale)), max(1, round(w * scale)))
    if min(size) < params.features.patch_size:
        return None
    return size


def _nearest(labels: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Integer maps ``(..., H, W)`` at ``size``: each pixel takes the label under its centre."""
    big_h, big_w = labels.shape[-2:]
    h, w = size
    dev = labels.device
    ys = ((torch.arange(h, device=dev) + 0.5) * (big_h / h)).long().clamp_max(big_h - 1)
    xs = ((torch.arange(w, device=dev) + 0.5) * (big_w / w)).long().clamp_max(big_w - 1)
    return labels[..., ys[:, None], xs[None, :]].contiguous()


def coarse_features(
    features: SemanticFeatures,
    working: tuple[int, int],
    size: tuple[int, int],
    params: Parameters,
) -> SemanticFeatures:
    """Stage 0's features of the working image (``working``, ``(H, W)``), for it at ``size``.

    The patch descriptors stay (their centres move with the image); the proposals' atoms and
    the segments take the label under each coarse pixel's centre, and the mid-level maps
    (``S_m``'s similarities, ``B``'s PCA features) are made again from those atoms, as Stage 0
    makes them. Features without the atoms (``midlevel`` ``None``, as a video's warped ones)
    have those maps area-averaged instead.
    """
    h, w = size
    centers = features.patch_centers
    if centers is not None:
        scale = torch.tensor([h / working[0], w / working[1]], device=centers.device)
        centers = (centers.to(torch.float64) * scale).round().long()
        top = torch.tensor([h - 1, w - 1], device=centers.device)
        centers = torch.minimum(centers.clamp_min(0), top)
    mid = features.midlevel
    similarity, gpca = features.similarity, features.gpca
    if isinstance(mid, MidLevelBatch):
        items = []
        for m in mid:
            labels = _nearest(m.atom_labels, size)
            sizes = torch.bincount(labels.flatten(), minlength=m.atom_g.shape[0])
            items.append(MidLevelFeatures(labels, m.atom_g, sizes.to(m.atom_sizes.dtype)))
        mid = MidLevelBatch(tuple(items))
        if similarity is not None:
            similarity = mid.similarity(shading_stencil(h, w, device=similarity.device))
        if gpca is not None:
            gpca = pca_features(mid, params.features.proposal_pca_dim)
    else:
        mid = None
        similarity = None if similarity is None else downsample(similarity, size)
        gpca = None if gpca is None else downsample(gpca, size)
    segments = None if features.segments is None else _nearest(features.segments, size)
    return SemanticFeatures(centers, features.patch_features, similarity, gpca, segments, mid, {})


def coarse_inputs(work: WorkingInputs, size: tuple[int, int]) -> WorkingInputs:
    """``work`` with its image and mask at ``size`` (area-averaged from the working image)."""
    image, mask = downsampled(work.image, work.mask, size)
    return WorkingInputs(work.full, work.full_mask, work.dtype, image, mask, 1)


def coarse_alternations(
    work: WorkingInputs,
    features: SemanticFeatures,
    params: Parameters,
    size: tuple[int, int],
    keep_layers: bool,
    done: Done,
    texture: torch.Tensor | None = None,
) -> Alternation:
    """Alternations ``1 .. k − 1`` at ``size``; ``done(k, run)`` after each.

    ``texture``: ``S_l``'s texture confidence at the working resolution, area-averaged to
    ``size`` here (``None``: made at ``size`` when ``t_x`` is on).
    """
    t0 = time.perf_counter()
    low = coarse_inputs(work, size)
    low_features = coarse_features(features, work.size, size, params)
    low_texture = None if texture is None else downsample(texture, size)
    run = Alternation(low, low_features, params, keep_layers, texture=low_texture)
    run.times["coarse inputs"] = time.perf_counter() - t0
    for k in range(1, params.iterations):
        shading, reflectance = params.alternation(k)
        run.shading_step(k, shading)
        run.reflectance_step(k, reflectance)
        done(k, run)
    return run


def _inside_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``x`` with the pixels outside ``mask`` set to each image's and channel's mean inside.

    Outside a mask a layer means nothing (0, or the log of the floor); a part of the mask too
    thin to survive at the coarse size takes the mean of the rest instead.
    """
    if mask is None:
        return x
    inside = mask.to(x.dtype)
    mean = (x * inside).sum((2, 3), keepdim=True) / inside.sum((2, 3), keepdim=True).clamp_min(1)
    return torch.where(mask, x, mean)


def _up(
    x: torch.Tensor, size: tuple[int, int], mask: torch.Tensor | None, big_mask: torch.Tensor | None
) -> torch.Tensor:
    """Bilinear ``x`` at ``size``; with masks, only the pixels inside enter, 0 outside."""
    if mask is None:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    inside = mask.to(x.dtype)
    x = _inside_mean(x, mask)
    num = F.interpolate(x * inside, size=size, mode="bilinear", align_corners=False)
    den = F.interpolate(inside, size=size, mode="bilinear", align_corners=False)
    far = F.interpolate(x, size=size, mode="nearest")  # no coarse pixel inside is near
    out = torch.where(den > 1e-6, num / den.clamp_min(1e-6), far)
    return out if big_mask is None else out * big_mask


def hand_over(coarse: Alternation, run: Alternation) -> None:
    """Start ``run`` (at the working resolution) where ``coarse`` ended.

    The coarse decomposition's shading (Stage 2's ``I / R``, with Stage 1's ``σ`` where
    pixels are dark, as its output would give it), brought up to the working size in the log
    domain by the output's guided filter, starts ``run``'s shading solve, as the shading of a
    warm start (``decompose(init=...)``) does. Stage 2 of that alternation starts from its
    ``ρ`` with a zero Bregman variable, and its matting base is the smoothed image, as in a
    first alternation: what the coarse run could not resolve (thin strokes, fine print) is
    decided at the working resolution. The coarse solves' reports (with their size) and times
    come first in ``run``'s, and the kept layers are brought up too.
    """
    params, low, work = run.params, coarse.work, run.work
    size = work.size
    if coarse.reflectance is None or coarse.sigma is None:
        raise ValueError("hand_over needs a coarse run of at least one alternation")
    floor, out, dark = params.reflectance.shading_floor, params.output, params.shading.dark_eps
    shading = final_shading(low.image, coarse.reflectance, coarse.sigma, params)
    # outside the coarse mask the shading means nothing (I = R = 0): those pixels stay out
    weight = None if low.mask is None else low.mask.to(shading.dtype)
    guide = log_luminance(work.image, dark)
    log_low = _inside_mean(shading.clamp_min(floor).log(), low.mask)
    up = GuidedUpsampler(
        log_low, log_luminance(low.image, dark), size, out.guide_radius, out.guide_eps,
        weight,
    )  # fmt: skip
    log_s = up.full(lambda rows: guide[:, :, rows])
    if work.mask is not None:
        log_s = log_s * work.mask
    run.work = replace(work, log_shading0=log_s.contiguous())
    run.solves[:0] = [replace(r, size=low.size) for r in coarse.solves]
    run.times = {**coarse.times, **run.times}
    low_mask, mask = low.mask, work.mask

    def layer(x: torch.Tensor, log: bool) -> torch.Tensor:
        if not log:
            return _up(x, size, low_mask, mask)
        up = _up(x.clamp_min(1e-30).log(), size, low_mask, None).exp()
        return up if mask is None else up * mask

    run.layers[:0] = [
        IterationLayers(
            layer(it.sigma, True),
            layer(it.rho, False),
            layer(it.reflectance, False),
            layer(it.shading, True),
        )  # fmt: skip
        for it in coarse.layers
    ]
