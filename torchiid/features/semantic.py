"""Stage 0 as one call: every semantic feature the two stages need, computed once per image.

:func:`semantic_features` runs the CNN patch features ``f_b`` (or patch-mean RGB for the
paper's strategies p1/p2), selective-search proposals and their mid-level features ``g_i``
(3x3 similarities for ``S_m`` and PCA ``g̊`` for ``B``), and the Felzenszwalb segments whose
representative pixels form ``Q`` for ``C``. What a switched-off prior does not need is skipped.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.params import Parameters
from torchiid.stages.config import ReflectanceProblem, ShadingProblem

__all__ = ["SemanticFeatures", "semantic_features", "patch_mean_rgb", "pca_features"]


@dataclass(frozen=True)
class SemanticFeatures:
    """What Stage 0 gives the two stages (``None`` where the prior using it is off).

    Attributes:
        patch_centers: ``(N, 2)`` long ``(y, x)`` patch centres (for ``S_c``).
        patch_features: ``(B, N, D)`` ``f_b`` (D = 1280) or patch-mean RGB (D = 3).
        similarity: ``(B, 4, H, W)`` ``<g_i, g_j>`` on the 3x3 stencil (for ``S_m``).
        gpca: ``(B, d, H, W)`` PCA-reduced ``g̊`` (for ``B``).
        segments: ``(B, H, W)`` long segment labels (for ``Q`` of ``C``).
        midlevel: the per-image mid-level features (for pictures), or ``None``.
        times: seconds per step. The segments' C++ segmentation runs in a thread while the
            proposals are computed, so ``times["segments"]`` counts only the time the caller
            spent on it (preparing, then waiting for the result).
    """

    patch_centers: torch.Tensor | None
    patch_features: torch.Tensor | None
    similarity: torch.Tensor | None
    gpca: torch.Tensor | None
    segments: torch.Tensor | None
    midlevel: object | None = None
    times: dict[str, float] = field(default_factory=dict)

    def shading_problem(
        self,
        image: torch.Tensor,
        base_image: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        texture: torch.Tensor | None = None,
    ) -> ShadingProblem:
        """Stage 1's problem on ``image`` with these features (``S_c``'s and ``S_m``'s inputs)."""
        return ShadingProblem(
            image=image,
            patch_centers=self.patch_centers,
            patch_features=self.patch_features,
            similarity=self.similarity,
            base_image=base_image,
            mask=mask,
            texture=texture,
        )

    def reflectance_problem(
        self, rho: torch.Tensor, image: torch.Tensor, mask: torch.Tensor | None = None
    ) -> ReflectanceProblem:
        """Stage 2's problem for ``rho`` (clamped at 0) with these features (``B``'s, ``C``'s)."""
        return ReflectanceProblem(
            rho=rho.clamp_min(0), image=image, gpca=self.gpca, segments=self.segments, mask=mask
        )


def patch_mean_rgb(image: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Mean colour of every patch box ``(x1, y1, x2, y2)`` via an integral image.

    Shape:
        image ``(B, 3, H, W)``, boxes ``(N, 4)`` -> ``(B, N, 3)``.
    """
    ii = F.pad(image.cumsum(-1).cumsum(-2), (1, 0, 1, 0))
    x1, y1, x2, y2 = (boxes[:, i].to(image.device) for i in range(4))
    s = ii[..., y2, x2] - ii[..., y1, x2] - ii[..., y2, x1] + ii[..., y1, x1]
    area = ((x2 - x1) * (y2 - y1)).to(image.dtype)
    return (s / area).transpose(1, 2)


def pca_features(mid, dim: int) -> torch.Tensor:
    """``g̊`` with ``dim`` channels for every image of a ``MidLevelBatch``.

    A featureless image (fewer proposals than ``dim``, e.g. one constant colour) gets the
    components it has and zeros for the rest, which add nothing to any distance.
    """
    out = []
    for item in mid:
        avail = min(dim, item.num_proposals)
        g = item.pca(avail)
        if avail < dim:
            g = torch.cat([g, g.new_zeros(g.shape[0], dim - avail, *g.shape[2:])], dim=1)
        out.append(g)
    return torch.cat(out)


def semantic_features(image: torch.Tensor, params: Parameters) -> SemanticFeatures:
    """Compute Stage 0 for a batch of linear RGB images ``(B, 3, H, W)``."""
    from torchiid.features.midlevel import midlevel_features_batch
    from torchiid.features.patches import patch_features, patch_grid
    from torchiid.features.proposals import selective_search
    from torchiid.features.segmentation import start_felzenszwalb_segments
    from torchiid.priors.shading_terms import shading_stencil

    times: dict[str, float] = {}
    image = image.contiguous()  # channels-last strides slow the per-pixel torch ops down
    b, _, h, w = image.shape
    centers = feats = sim = gpca = segs = mid = None
    # Stage 0 computes what the active priors need (the weights carry the switches)
    shading_w, refl_w = params.shading.weights(), params.reflectance.weights()
    need_sc = shading_w["S_c"] > 0
    need_sim = shading_w["S_m"] > 0
    need_gpca = refl_w["B"] > 0
    f = params.features
    need_g = need_sim or need_gpca
    if need_sc:
        t0 = time.perf_counter()
        grid = patch_grid(h, w, f.patch_size, f.patch_stride)
        centers = grid.centers.to(image.device)
        if f.lle_features == "cnn":
            feats = patch_features(
                image,
                mode=f.feature_mode,
                backend=f.feature_backend,
                size=f.patch_size,
                stride=f.patch_stride,
            ).features
        else:
            feats = patch_mean_rgb(image, grid.boxes)
        times["patch features"] = time.perf_counter() - t0
    pool = seg_result = None
    if refl_w["C"] > 0:
        # the segments' C++ segmentation runs in a thread, overlapping the proposals
        t0 = time.perf_counter()
        pool = ThreadPoolExecutor(max_workers=1) if need_g else None
        seg_result = start_felzenszwalb_segments(image, scale=f.segment_scale, executor=pool)
        times["segments"] = time.perf_counter() - t0
    try:
        if need_g:
            t0 = time.perf_counter()
            props = selective_search(image.detach().cpu(), seed=params.seed)
            times["proposals"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            mid = midlevel_features_batch(props, like=image)
            if need_sim:
                sim = mid.similarity(shading_stencil(h, w, device=image.device))
            if need_gpca:
                gpca = pca_features(mid, f.proposal_pca_dim)
            times["mid-level g"] = time.perf_counter() - t0
        if seg_result is not None:
            t0 = time.perf_counter()
            segs = seg_result()
            times["segments"] += time.perf_counter() - t0
    finally:  # also when the proposals fail: no thread is left behind
        if pool is not None:
            pool.shutdown()
    return SemanticFeatures(centers, feats, sim, gpca, segs, mid, times)
