"""Coarse-to-fine alternations: all but the last at a fraction of the working resolution.

The §3.4 schedule's alternations refine one answer: each starts from the previous shading
(the shading PCG's warm start) and reflectance (the next matting base and the Split-Bregman
start). With ``params.coarse_scale`` below 1 the alternations ``1 .. k − 1`` run on the image
brought to that fraction of the working resolution's sides, and their last shading and
reflectance, brought back up, start alternation ``k`` at the working resolution. The energy
of every alternation is the paper's; only where its solves start changes.

Stage 0 runs once, at the working resolution: the coarse alternations take its features
resampled (:func:`coarse_features`), so the CNN and the proposals are not run twice.

It applies to a cold decomposition only: a warm start (``init``), a temporal prior or a
``schedule_start`` after 1 already says where the solves start, and a coarse size whose
shorter side falls below the patch size runs every alternation at the working resolution.
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
from torchiid.resample import GuidedUpsampler

__all__ = ["coarse_size", "coarse_features", "coarse_alternations", "hand_over"]

#: called after each alternation ``k`` of the coarse run, with the run
Done = Callable[[int, Alternation], None]


def coarse_size(work: WorkingInputs, params: Parameters) -> tuple[int, int] | None:
    """The size the alternations before the last run at, or ``None`` for the working size.

    ``None`` when ``params.coarse_scale`` is 1, for a single alternation, for a warm start, a
    temporal prior or a later ``schedule_start``, and when the coarse image's shorter side
    would be below ``params.features.patch_size``.
    """
    scale = params.coarse_scale
    if scale >= 1 or params.iterations < 2 or work.first != 1:
        return None
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
    features: SemanticFeatures, size: tuple[int, int], params: Parameters
) -> SemanticFeatures:
    """Stage 0's features of the working image, for the same image at ``size``.

    The patch descriptors stay (their centres move with the image); the proposals' atoms and
    the segments take the label under each coarse pixel's centre, and the mid-level maps
    (``S_m``'s similarities, ``B``'s PCA features) are made again from those atoms, as Stage 0
    makes them.
    """
    h, w = size
    centers = features.patch_centers
    if centers is not None:
        big_h, big_w = _feature_size(features)
        scale = torch.tensor([h / big_h, w / big_w], device=centers.device)
        centers = (centers.to(torch.float64) * scale).round().long()
        top = torch.tensor([h - 1, w - 1], device=centers.device)
        centers = torch.minimum(centers.clamp_min(0), top)
    mid = features.midlevel
    if isinstance(mid, MidLevelBatch):
        items = []
        for m in mid:
            labels = _nearest(m.atom_labels, size)
            sizes = torch.bincount(labels.flatten(), minlength=m.atom_g.shape[0])
            items.append(MidLevelFeatures(labels, m.atom_g, sizes.to(m.atom_sizes.dtype)))
        mid = MidLevelBatch(tuple(items))
    similarity = gpca = None
    if features.similarity is not None:
        similarity = _need_mid(mid).similarity(shading_stencil(h, w, device=_device(features)))
    if features.gpca is not None:
        gpca = pca_features(_need_mid(mid), params.features.proposal_pca_dim)
    segments = None if features.segments is None else _nearest(features.segments, size)
    return SemanticFeatures(centers, features.patch_features, similarity, gpca, segments, mid, {})


def _feature_size(features: SemanticFeatures) -> tuple[int, int]:
    for x in (features.similarity, features.gpca, features.segments):
        if x is not None:
            return int(x.shape[-2]), int(x.shape[-1])
    if isinstance(features.midlevel, MidLevelBatch):
        return features.midlevel[0].shape
    raise ValueError("the features hold no map to take the working size from")


def _device(features: SemanticFeatures) -> torch.device:
    x = features.similarity if features.similarity is not None else features.gpca
    return x.device if x is not None else torch.device("cpu")


def _need_mid(mid: object) -> MidLevelBatch:
    if not isinstance(mid, MidLevelBatch):
        raise ValueError("the mid-level maps cannot be resampled without Stage 0's atoms")
    return mid


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
) -> Alternation:
    """Alternations ``1 .. k − 1`` at ``size``; ``done(k, run)`` after each."""
    t0 = time.perf_counter()
    low = coarse_inputs(work, size)
    run = Alternation(low, coarse_features(features, size, params), params, keep_layers)
    run.times["coarse inputs"] = time.perf_counter() - t0
    for k in range(1, params.iterations):
        shading, reflectance = params.alternation(k)
        run.shading_step(k, shading)
        run.reflectance_step(k, reflectance)
        done(k, run)
    return run


def _up(
    x: torch.Tensor, size: tuple[int, int], mask: torch.Tensor | None, big_mask: torch.Tensor | None
) -> torch.Tensor:
    """Bilinear ``x`` at ``size``; with masks, only the pixels inside enter, 0 outside."""
    if mask is None:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    inside = mask.to(x.dtype)
    num = F.interpolate(x * inside, size=size, mode="bilinear", align_corners=False)
    den = F.interpolate(inside, size=size, mode="bilinear", align_corners=False)
    near = F.interpolate(x, size=size, mode="nearest")  # where no coarse pixel inside is near
    out = torch.where(den > 1e-6, num / den.clamp_min(1e-6), near)
    return out if big_mask is None else out * big_mask


def hand_over(coarse: Alternation, run: Alternation) -> None:
    """Start ``run`` (at the working resolution) where ``coarse`` ended.

    The coarse decomposition's shading (Stage 2's ``I / R``, with Stage 1's ``σ`` where
    pixels are dark, as its output would give it), brought up to the working size in the log
    domain by the output's guided filter, starts ``run``'s shading solve, as the shading of a
    warm start (``decompose(init=...)``) does. Stage 2 of that alternation starts from its
    ``ρ`` with a zero Bregman variable, and its matting base is the smoothed image, as in a
    first alternation: what the coarse run could not resolve (thin strokes, fine print) is
    decided at the working resolution. The coarse solves' reports and times come first in
    ``run``'s, and the kept layers are brought up too.
    """
    params, low, work = run.params, coarse.work, run.work
    size = work.size
    if coarse.reflectance is not None and coarse.sigma is not None:
        floor, out, dark = params.reflectance.shading_floor, params.output, params.shading.dark_eps
        shading = final_shading(low.image, coarse.reflectance, coarse.sigma, params)
        # outside the coarse mask the shading means nothing (I = R = 0): those pixels stay out
        weight = None if low.mask is None else low.mask.to(shading.dtype)
        guide = log_luminance(work.image, dark)
        up = GuidedUpsampler(
            shading.clamp_min(floor).log(), log_luminance(low.image, dark), size,
            out.guide_radius, out.guide_eps, weight,
        )  # fmt: skip
        log_s = up.full(lambda rows: guide[:, :, rows])
        if work.mask is not None:
            log_s = log_s * work.mask
        run.work = replace(work, log_shading0=log_s.contiguous())
    run.solves[:0] = coarse.solves
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
