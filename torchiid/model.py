"""The whole method (Saini & Narayanan, §3 and §3.4).

Stage 0 features, then k alternations of Stage 1 (L2 shading) and Stage 2 (L1 reflectance).

:func:`decompose` is the functional core and :class:`IntrinsicDecomposer` its ``nn.Module``
twin. Both take **linear** RGB ``(B, 3, H, W)`` tensors on any device and return a
:class:`Decomposition` whose layers satisfy ``image == reflectance * shading`` exactly (up to
floating-point rounding) inside the mask.

Scale: the product ``R · S`` is ambiguous up to a factor. The returned shading is gray and
scaled so that its 99th percentile inside the mask is 1 (bright lit surfaces have shading 1 and
the reflectance there equals the image); the reflectance is then ``I / S``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from torchiid.core.check import check_image, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.semantic import SemanticFeatures, semantic_features
from torchiid.params import Parameters
from torchiid.resample import downsample, guided_upsample, working_size

__all__ = ["Decomposition", "IterationLayers", "decompose", "IntrinsicDecomposer"]

_SHADING_FLOOR = 1e-4


@dataclass(frozen=True)
class IterationLayers:
    """The layers of one alternation (paper Fig. 5), linear, at the working resolution.

    Attributes:
        sigma: ``(B, 1, h, w)`` Stage 1 shading ``σ``.
        rho: ``(B, 3, h, w)`` Stage 1 reflectance ``ρ = I / σ``.
        R: ``(B, 3, h, w)`` Stage 2 reflectance.
        S: ``(B, 1, h, w)`` Stage 2 shading (gray ``I / R``).
    """

    sigma: torch.Tensor
    rho: torch.Tensor
    R: torch.Tensor
    S: torch.Tensor


@dataclass(frozen=True)
class Decomposition:
    """Result of :func:`decompose`; every layer is **linear** RGB / gray.

    Attributes:
        reflectance: ``(B, 3, H, W)`` final reflectance ``R`` (0 outside the mask).
        shading: ``(B, 1, H, W)`` final gray shading ``S`` (0 outside the mask);
            ``reflectance * shading == image`` inside the mask.
        sigma: ``(B, 1, H, W)`` last Stage 1 shading ``σ`` (same normalisation as ``shading``).
        rho: ``(B, 3, H, W)`` last Stage 1 reflectance ``ρ = I / σ``.
        iterations: every alternation's layers if asked for, else an empty tuple.
        params: the parameters used.
        times: seconds per step (``"patch features"``, ``"proposals"``, ...,
            ``"shading k"``, ``"reflectance k"``, ``"total"``).
        mask: ``(B, 1, H, W)`` bool mask used, or ``None``.
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    sigma: torch.Tensor
    rho: torch.Tensor
    iterations: tuple[IterationLayers, ...]
    params: Parameters
    times: dict[str, float] = field(default_factory=dict)
    mask: torch.Tensor | None = None


def _percentile_scale(s: torch.Tensor, mask: torch.Tensor | None, q: float = 0.99) -> torch.Tensor:
    """Per-image ``q``-quantile of ``s`` inside the mask, ``(B, 1, 1, 1)``."""
    out = []
    for i in range(s.shape[0]):
        v = s[i].reshape(-1) if mask is None else s[i][mask[i]].reshape(-1)
        if v.numel() > 200_000:  # quantile of a deterministic subsample keeps this cheap
            v = v[:: v.numel() // 200_000 + 1]
        out.append(torch.quantile(v.float(), q).to(s.dtype))
    return torch.stack(out).view(-1, 1, 1, 1).clamp_min(_SHADING_FLOOR)


def _gray_shading(image: torch.Tensor, refl: torch.Tensor) -> torch.Tensor:
    """Gray ``S = Σ_c I_c / Σ_c R_c`` (the least-squares-like gray ratio), floored."""
    s = image.sum(1, keepdim=True) / refl.sum(1, keepdim=True).clamp_min(_SHADING_FLOOR)
    return s.clamp_min(_SHADING_FLOOR)


def _log_luminance(image: torch.Tensor, eps: float) -> torch.Tensor:
    y = 0.2126 * image[:, :1] + 0.7152 * image[:, 1:2] + 0.0722 * image[:, 2:3]
    return y.clamp_min(eps).log()


def _check_inputs(
    image: torch.Tensor, mask: torch.Tensor | None, params: Parameters
) -> tuple[torch.Tensor, torch.Tensor | None]:
    if isinstance(image, torch.Tensor) and image.dim() == 3:
        image = image[None]
    check_image(image, "image", min_side=params.patch_size)
    if mask is not None:
        if mask.dim() == 3:
            mask = mask[None]
        check_shape(mask, (image.shape[0], 1, image.shape[2], image.shape[3]), "mask")
        if mask.dtype != torch.bool:
            raise ShapeError(f"expected a bool mask, got {mask.dtype}; use mask > 0.5")
        mask = mask.to(image.device)
        empty = ~mask.flatten(1).any(1)
        if bool(empty.any()):
            raise ShapeError(f"mask of image {int(empty.nonzero()[0])} is empty (no pixel inside)")
    return image, mask


@torch.no_grad()
def decompose(
    image: torch.Tensor,
    params: Parameters | None = None,
    *,
    mask: torch.Tensor | None = None,
    features: SemanticFeatures | None = None,
    return_iterations: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
) -> Decomposition:
    """Decompose linear RGB images into reflectance and shading (the paper's full method).

    Args:
        image: ``(B, 3, H, W)`` or ``(3, H, W)`` **linear** RGB, values ``>= 0`` (typically in
            ``[0, 1]``), sides of at least ``params.patch_size`` pixels. Images of a batch are
            solved together as one block-diagonal system.
        params: :class:`~torchiid.params.Parameters` (default: the ``default`` preset).
        mask: optional ``(B, 1, H, W)`` bool; every prior is restricted to the pixels inside
            and the outside is returned as 0.
        features: precomputed Stage 0 features (at the working resolution), e.g. to run
            several parameter sets on one image.
        return_iterations: keep every alternation's ``σ, ρ, R, S`` (paper Fig. 5).
        progress: called as ``progress(stage, k, total)`` with stage ``"features"`` and then
            ``"iteration"`` after each alternation ``k = 1..total``.

    Returns:
        :class:`Decomposition`. Outputs are detached (the method is an optimisation, not a
        differentiable layer).

    Example:
        >>> from torchiid.synthetic import mondrian
        >>> img = mondrian(64, 64).image
        >>> p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
        >>> out = decompose(img, p)
        >>> out.reflectance.shape, out.shading.shape
        (torch.Size([1, 3, 64, 64]), torch.Size([1, 1, 64, 64]))
        >>> bool(torch.allclose(out.reflectance * out.shading, img, atol=1e-5))
        True
    """
    from torchiid.stages.reflectance import ReflectanceCache, solve_reflectance
    from torchiid.stages.shading import ShadingSystemCache, solve_shading

    params = params if params is not None else Parameters.preset("default")
    t_start = time.perf_counter()
    image, mask = _check_inputs(image, mask, params)
    big_h, big_w = image.shape[-2:]
    h, w = working_size(big_h, big_w, params.max_side)
    img = downsample(image, (h, w))
    msk = None
    if mask is not None:
        frac = downsample(mask.to(image.dtype), (h, w))
        msk = frac > 0.5
        tiny = ~msk.flatten(1).any(1)  # a small mask can vanish at the working resolution
        msk[tiny] = frac[tiny] > 0
        # the outside is blacked out so that it cannot influence any prior
        img = img * msk
    if min(h, w) < params.patch_size:
        raise ParameterError(
            f"working resolution {w}x{h} (max_side={params.max_side}) is smaller than the "
            f"{params.patch_size} px patches; raise max_side or lower patch_size"
        )
    if features is None:
        features = semantic_features(img, params)
    times = dict(features.times)
    if progress is not None:
        progress("features", 0, params.iterations)

    lam_g, lam_m, lam_l = params.lambda_g, params.lambda_m, params.lambda_l
    gam_l, gam_m, gam_g, gam_a = params.gamma_l, params.gamma_m, params.gamma_g, params.gamma_a
    use_g = params.use_sc or params.use_sp
    s_prev = r_prev = None
    sigma = rho = refl = None
    shading_cache = ShadingSystemCache()  # S_c, S_m, S_l are built once per image
    reflectance_cache = ReflectanceCache()  # and B's proposal-feature factor
    layers: list[IterationLayers] = []
    for k in range(1, params.iterations + 1):
        t0 = time.perf_counter()
        if params.stage1:
            sh = solve_shading(
                img,
                patch_centers=features.patch_centers if params.use_sc else None,
                patch_features=features.patch_features if params.use_sc else None,
                similarity=features.similarity if params.use_sm else None,
                base_image=r_prev if params.use_sp else None,
                mask=msk,
                lambda_g=lam_g if use_g else 0.0,
                lambda_m=lam_m if params.use_sm else 0.0,
                lambda_l=lam_l if params.use_sl else 0.0,
                use_sc=params.use_sc and features.patch_features is not None,
                use_sp=params.use_sp,
                t_c=params.t_c,
                t_b=params.t_b,
                t_m=params.t_m,
                matting_eps=params.matting_eps,
                dark_eps=params.dark_eps,
                lle_k=params.lle_k,
                lle_reg=params.lle_reg,
                lle_neighbours=params.lle_neighbours,
                seed=params.seed,
                x0=s_prev,
                tol=params.cg_tol,
                max_iter=(
                    (params.warm_cg_max_iter or params.cg_max_iter)
                    if s_prev is not None
                    else params.cg_max_iter
                ),
                warn=False,
                levels=1 if s_prev is not None else 3,
                cache=shading_cache,
            )
            s_prev = sh.log_shading
            sigma, rho = sh.shading, sh.reflectance
        else:
            # baseline 2/3: no shading stage; Stage 2 flattens its own previous result
            rho = img if r_prev is None else r_prev
            sigma = _gray_shading(img, rho)
        times[f"shading {k}"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if params.stage2:
            rr = solve_reflectance(
                rho.clamp_min(0),
                img,
                gpca=features.gpca if params.use_rm else None,
                segments=features.segments if params.use_rg else None,
                mask=msk,
                gamma_l=gam_l if params.use_rl else 0.0,
                gamma_m=gam_m if params.use_rm else 0.0,
                gamma_g=gam_g if params.use_rg else 0.0,
                gamma_a=gam_a,
                theta=params.theta,
                t=params.t,
                colour_weights=params.colour_weights,
                z0=r_prev,
                tol=params.bregman_tol,
                max_outer=params.bregman_iter,
                cg_max_iter=params.bregman_cg_iter,
                track_objective=False,
                cache=reflectance_cache,
            )
            refl = rr.reflectance
        else:
            refl = rho
        times[f"reflectance {k}"] = time.perf_counter() - t0
        r_prev = refl
        if return_iterations:
            layers.append(IterationLayers(sigma=sigma, rho=rho, R=refl, S=_gray_shading(img, refl)))
        # §3.4: strengthen mid-level, global and data terms, weaken local ones
        lam_g, lam_m, gam_m, gam_g, gam_a = (
            x * params.tau for x in (lam_g, lam_m, gam_m, gam_g, gam_a)
        )
        lam_l, gam_l = lam_l / params.tau, gam_l / params.tau
        if progress is not None:
            progress("iteration", k, params.iterations)

    # final layers at full resolution, I = R * S exactly, S gray with 99th percentile 1
    log_s = _gray_shading(img, refl).log()
    if (h, w) != (big_h, big_w):
        log_s = guided_upsample(
            log_s, _log_luminance(img, params.dark_eps), _log_luminance(image, params.dark_eps)
        )
    shading = log_s.exp()
    scale = _percentile_scale(shading, mask)
    shading = (shading / scale).clamp_min(_SHADING_FLOOR)
    reflectance = image / shading
    sig = sigma / _percentile_scale(sigma, msk)
    if (h, w) != (big_h, big_w):
        sig = guided_upsample(
            sig.clamp_min(_SHADING_FLOOR).log(),
            _log_luminance(img, params.dark_eps),
            _log_luminance(image, params.dark_eps),
        ).exp()
    sig = sig.clamp_min(_SHADING_FLOOR)
    rho_full = image / sig
    if mask is not None:
        keep = mask.to(image.dtype)
        reflectance, shading = reflectance * keep, shading * keep
        sig, rho_full = sig * keep, rho_full * keep
    times["total"] = time.perf_counter() - t_start
    return Decomposition(
        reflectance=reflectance,
        shading=shading,
        sigma=sig,
        rho=rho_full,
        iterations=tuple(layers),
        params=params,
        times=times,
        mask=mask,
    )


class IntrinsicDecomposer(nn.Module):
    """``nn.Module`` twin of :func:`decompose` for use inside larger models.

    Args:
        params: the parameters (default: the ``default`` preset).
        return_iterations: keep every alternation's layers.

    Shape:
        input ``(B, 3, H, W)`` linear RGB; output :class:`Decomposition` with reflectance
        ``(B, 3, H, W)`` and shading ``(B, 1, H, W)``.

    Example:
        >>> from torchiid.synthetic import mondrian
        >>> p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
        >>> out = IntrinsicDecomposer(p)(mondrian(64, 64).image)
        >>> out.shading.shape
        torch.Size([1, 1, 64, 64])
    """

    def __init__(self, params: Parameters | None = None, return_iterations: bool = False):
        super().__init__()
        self.params = params if params is not None else Parameters.preset("default")
        self.return_iterations = return_iterations

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> Decomposition:
        """Decompose ``image``; see :func:`decompose`."""
        return decompose(image, self.params, mask=mask, return_iterations=self.return_iterations)
