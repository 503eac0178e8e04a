"""Colour features and pair affinities of the reflectance priors (paper §3.3, Eqs. 7–10).

Colour features (Eq. 7): ``r̄ = (w_L · L/s_L, a/s_a, b/s_b)`` from CIELab of the linear
reflectance (:func:`lab_features`), in one of two scalings (:data:`COLOUR_WEIGHTS`):

- ``"wide"``: ``(0.1·L/100, a/220, b/220)``. Luminance counts ten times less than chroma, and a
  chroma step of ``Δa ≈ 11`` gives ``‖Δr̄‖ = 0.05 = t``, a weight ``exp(−1/2) ≈ 0.61``;
  ``Δa ≈ 33`` gives ``0.011``.
- ``"bi"`` (the default of :class:`~torchiid.params.Parameters`): ``(0.5·L/100, a/36.7, b/36.7)``,
  i.e. ``t·(μ·L/100, γ·a/220, γ·b/220)`` with Bi et al.'s ``μ = 10``, ``γ = 120`` (their
  ``windowvariation.m`` weighs pairs by ``exp(−½‖(μ·L/100, γ·a/220, γ·b/220)‖²)``): at the
  paper's ``t = 0.05`` the weights are exactly Bi et al.'s, whose parameters the paper says it
  reuses. ``ΔL = 10`` or ``Δa ≈ 1.8`` gives a weight 0.61, ``ΔL = 30`` or ``Δa ≈ 5.5`` gives
  0.011: 5–6× narrower than ``"wide"``, so texture and thin coloured prints survive the
  flattening.

Weights below ``e^MIN_EXPONENT`` (``e^-30 ≈ 1e-13``) are 0. Against the data term such a pair
changes nothing in float32 (its weight, squared in the ``z`` step, is ~1e-26 of the data
weight), but the squares and products of weights that small are subnormal numbers, which x86
CPUs process through a slow microcode path.

Masks: a ``(B, 1, H, W)`` bool ``mask`` gives 0 to every pair touching a pixel outside it.
"""

from __future__ import annotations

import math

import torch

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors import kernels
from torchiid.priors.stencil import Stencil, shift_slices

__all__ = [
    "COLOUR_WEIGHTS",
    "MIN_EXPONENT",
    "lab_features",
    "stencil_affinity",
    "merged_stencil_affinity",
    "pair_affinity",
]

#: exponent below which a colour affinity ``exp(−‖Δf‖²/2t²)`` is 0 (see the module notes)
MIN_EXPONENT = -30.0


#: ``(w_L, (s_L, s_a, s_b))`` of :func:`lab_features` for each colour-weight scaling.
COLOUR_WEIGHTS: dict[str, tuple[float, tuple[float, float, float]]] = {
    "bi": (0.05 * 10.0, (100.0, 220.0 / (0.05 * 120.0), 220.0 / (0.05 * 120.0))),
    "wide": (0.1, (100.0, 220.0, 220.0)),
}


def lab_features(
    rgb: torch.Tensor,
    luminance_weight: float = COLOUR_WEIGHTS["bi"][0],
    lab_scale: tuple[float, float, float] = COLOUR_WEIGHTS["bi"][1],
    white_quantile: float = 0.99,
) -> torch.Tensor:
    """Channel-normalised CIELab with suppressed luminance, ``r̄`` of Eq. 7.

    The linear input is first divided by its per-image ``white_quantile`` of the channel maximum
    (when that exceeds 1; reflectance has an arbitrary scale) and clamped to ``[0, 1]``, then
    encoded to sRGB (:func:`torchiid.core.colour.linear_to_srgb`) and converted with
    ``kornia.color.rgb_to_lab`` (D65). Output: ``(w_L · L / s_L, a / s_a, b / s_b)``.

    Args:
        rgb: linear RGB (reflectance or image), ``>= 0``.
        luminance_weight: ``w_L``, the weight of lightness relative to chroma (default:
            ``COLOUR_WEIGHTS["bi"]``, 0.5).
        lab_scale: divisors ``(s_L, s_a, s_b)`` (default ``COLOUR_WEIGHTS["bi"]``,
            ``(100, 36.7, 36.7)``).
        white_quantile: quantile of the per-pixel channel maximum mapped to 1.

    Shape:
        ``(B, 3, H, W) -> (B, 3, H, W)``.
    """
    b = rgb.shape[0]
    peak = rgb.amax(dim=1).reshape(b, -1)
    k = max(1, min(peak.shape[1], round(white_quantile * peak.shape[1])))
    white = peak.kthvalue(k, dim=1).values.clamp_min(1.0).view(b, 1, 1, 1)
    srgb = linear_to_srgb(rgb / white)  # clamped to [0, 1] first
    # imported here, not with the module: its 20 MB are then not resident yet during Stage 0's
    # CNN pass, one of a decomposition's peaks of memory
    import kornia

    lab = kornia.color.rgb_to_lab(srgb)
    scale = torch.tensor(
        [luminance_weight / lab_scale[0], 1.0 / lab_scale[1], 1.0 / lab_scale[2]],
        device=rgb.device,
        dtype=rgb.dtype,
    )
    return lab * scale.view(1, 3, 1, 1)


def _floored_exp(v: torch.Tensor) -> torch.Tensor:
    """``exp(v)``, 0 where ``v < MIN_EXPONENT`` (in place on ``v``)."""
    return v.masked_fill_(v < MIN_EXPONENT, -math.inf).exp_()


def _check_t(t: float) -> None:
    if not t > 0:
        raise ParameterError(f"the weight deviation t must be > 0, got {t}")


def _bool(mask: torch.Tensor | None) -> torch.Tensor | None:
    return None if mask is None else mask.to(torch.bool)


def stencil_affinity(
    features: torch.Tensor, stencil: Stencil, t: float, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """``exp(−‖f_i − f_j‖² / 2t²)`` for every stencil pair (Eqs. 7–8).

    ``v^l = stencil_affinity(r̄)``; ``v^m = stencil_affinity(r̄) · stencil_affinity(g̊)``.
    Pairs leaving the image, or touching a pixel outside ``mask``, get 0.

    Args:
        features: per-pixel features ``f``.
        stencil: the pairs (e.g. ``Stencil.square(H, W, 11)``).
        t: deviation.
        mask: optional bool mask of the pixels to use.

    Shape:
        features ``(B, D, H, W)``, mask ``(B, 1, H, W)`` -> weights ``(B, K, H, W)`` in ``[0, 1]``.
    """
    _check_t(t)
    b, _, h, w = features.shape
    scale = -1.0 / (2.0 * t * t)
    cpu_mask = mask is None or mask.device.type == "cpu"
    if kernels.usable(features, offsets=stencil.offsets) and cpu_mask:
        return kernels.stencil_affinity(
            features, stencil.offsets, scale, mask=_bool(mask), min_exponent=MIN_EXPONENT
        )
    out = features.new_zeros(b, stencil.num_offsets, h, w)
    for k, (dy, dx) in enumerate(stencil.offsets):
        yi, xi, yj, xj = shift_slices(dy, dx, h, w)
        d = features[:, :, yi, xi] - features[:, :, yj, xj]
        v = _floored_exp(d.square().sum(dim=1) * scale)
        if mask is not None:
            v = v * (mask[:, 0, yi, xi] & mask[:, 0, yj, xj]).to(v.dtype)
        out[:, k, yi, xi] = v
    return out


def merged_stencil_affinity(
    colour: torch.Tensor,
    semantic_affinity: torch.Tensor,
    stencil: Stencil,
    t: float,
    gamma_l: float,
    gamma_m: float,
    mask: torch.Tensor | None = None,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Weights ``v̂ = (γ_l v^l + γ_m v^m) / (γ_l + γ_m)`` of ``A`` and ``B`` merged (Eqs. 8–9).

    ``v^l = exp(−‖Δr̄‖²/2t²)`` and ``v^m = v^l · e^g`` with the proposal-feature factor
    ``e^g = exp(−‖Δg̊‖²/2t_g²)`` share their pairs, so
    ``γ_l‖diag(v^l) M z‖₁ + γ_m‖diag(v^m) M z‖₁ = (γ_l + γ_m)‖diag(v̂) M z‖₁`` exactly and
    ``v̂ = v^l · (γ_l + γ_m e^g) / (γ_l + γ_m)``. ``e^g`` depends only on ``g̊``, which Stage 0
    computes once, so callers pass it precomputed (``stencil_affinity(g̊, stencil, t_g, mask)``)
    and reuse it across the alternations; one pass over the offsets then gives ``v̂`` without
    a second ``(B, K, H, W)`` tensor. ``out`` (optional, ``(B, K, H, W)``, the dtype and
    device of ``colour``) receives the result instead of a new tensor; it may be
    ``semantic_affinity`` itself (contiguous), whose factor the weights then replace, so that
    a caller that does not keep the factor needs no second tensor of that size.

    Shape:
        colour ``(B, 3, H, W)``, semantic_affinity ``(B, K, H, W)``, mask ``(B, 1, H, W)`` ->
        ``(B, K, H, W)``.
    """
    _check_t(t)
    if not gamma_l + gamma_m > 0:
        raise ParameterError(f"need gamma_l + gamma_m > 0, got {gamma_l} and {gamma_m}")
    b, _, h, w = colour.shape
    if semantic_affinity.shape != (b, stencil.num_offsets, h, w):
        raise ShapeError(
            f"semantic_affinity has shape {tuple(semantic_affinity.shape)}, expected "
            f"{(b, stencil.num_offsets, h, w)}"
        )
    sc = -1.0 / (2.0 * t * t)
    a_l, a_m = gamma_l / (gamma_l + gamma_m), gamma_m / (gamma_l + gamma_m)
    shape = (b, stencil.num_offsets, h, w)
    if out is not None and (out.shape != shape or out.dtype != colour.dtype):
        raise ShapeError(
            f"out must be a {colour.dtype} tensor of shape {shape} (batch, offsets, height, "
            f"width), got {out.dtype} of shape {tuple(out.shape)}"
        )
    if out is not None and out.data_ptr() == semantic_affinity.data_ptr():
        same = out.shape == semantic_affinity.shape and out.stride() == semantic_affinity.stride()
        if not (same and out.is_contiguous()):
            raise ShapeError(
                "out shares memory with semantic_affinity but is another view of it: pass "
                "semantic_affinity itself (contiguous) to write the weights over the factor, "
                "or a tensor of its own"
            )
    cpu_mask = mask is None or mask.device.type == "cpu"
    if kernels.usable(colour, semantic_affinity, offsets=stencil.offsets) and cpu_mask:
        return kernels.stencil_affinity(
            colour,
            stencil.offsets,
            sc,
            semantic_affinity,
            a_l,
            a_m,
            mask=_bool(mask),
            out=out,
            min_exponent=MIN_EXPONENT,
        )
    fresh = out is None
    out = colour.new_zeros(shape) if out is None else out
    for k, (dy, dx) in enumerate(stencil.offsets):
        yi, xi, yj, xj = shift_slices(dy, dx, h, w)
        dc = (colour[:, :, yi, xi] - colour[:, :, yj, xj]).square_().sum(dim=1)
        v = (
            torch.mul(semantic_affinity[:, k, yi, xi], a_m)
            .add_(a_l)
            .mul_(_floored_exp(dc.mul_(sc)))
        )
        if mask is not None:
            v.mul_(mask[:, 0, yi, xi] & mask[:, 0, yj, xj])
        if not fresh:  # zeroed only now: ``out`` may be ``semantic_affinity``, read above
            out[:, k].zero_()
        out[:, k, yi, xi] = v
    return out


def pair_affinity(
    features: torch.Tensor, i: torch.Tensor, j: torch.Tensor, t: float
) -> torch.Tensor:
    """``exp(−‖f_i − f_j‖² / 2t²)`` for listed pairs (``v^g`` of Eq. 10 on ``r̄``).

    Shape:
        features ``(B, D, H, W)``, flat pixel indices ``i, j`` ``(B, P)`` -> ``(B, P)``.
    """
    _check_t(t)
    b, d = features.shape[:2]
    f = features.reshape(b, d, -1)
    fi = f.gather(2, i.unsqueeze(1).expand(b, d, i.shape[1]))
    fj = f.gather(2, j.unsqueeze(1).expand(b, d, j.shape[1]))
    return _floored_exp((fi - fj).square().sum(dim=1) * (-1.0 / (2.0 * t * t)))
