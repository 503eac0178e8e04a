"""Weighted L1 terms of the reflectance formulation (paper §3.3, Eqs. 6–11).

The reflectance energy (Eq. 6/12) is ``π = γ_l ‖A z‖₁ + γ_m ‖B z‖₁ + γ_g ‖C z‖₁ + γ_a ‖z − ρ‖²``
over the 3-channel linear reflectance ``z``. Every L1 term is a weighted pair-difference operator
``diag(v) M`` applied to each channel separately (anisotropic L1): row ``(i, j)`` of ``M z`` is
``z_i − z_j`` and ``v_ij ∈ [0, 1]`` its weight (Eq. 7).

- :class:`StencilL1Term` holds ``A`` and ``B``: the pairs of an 11×11 window
  (:class:`~torchiid.priors.stencil.Stencil`), weights ``(B, K, H, W)``. Its hot paths
  (:meth:`~StencilL1Term.normal_matvec`, :meth:`~StencilL1Term.bregman_step`) loop over the ``K``
  offsets with slices and never materialise the ``(B, C, K, H, W)`` differences.
- :class:`PairL1Term` holds ``C``: an arbitrary list of pairs per image, ``(B, P)`` indices
  padded with zero-weight pairs, applied with ``gather``/``scatter_add``.

Both expose ``matrix()``, the operator ``diag(v) M`` as a torch sparse COO matrix (block diagonal
over the batch, acting on one channel), the canonical reference the fast paths are tested against.

Colour features (Eq. 7): ``r̄ = (w_L · L/s_L, a/s_a, b/s_b)`` from CIELab of the linear
reflectance (:func:`lab_features`), in one of two scalings (:data:`COLOUR_WEIGHTS`):

- ``"wide"``: ``(0.1·L/100, a/220, b/220)``. Luminance counts ten times less than chroma, and a
  chroma step of ``Δa ≈ 11`` gives ``‖Δr̄‖ = 0.05 = t``, a weight ``exp(−1/2) ≈ 0.61``;
  ``Δa ≈ 33`` gives ``0.011``.
- ``"bi"`` (the default of :class:`~torchiid.params.Parameters`): ``(0.5·L/100, a/36.7, b/36.7)``,
  i.e. ``t·(μ·L/100, γ·a/220, γ·b/220)`` with Bi et al.'s
  ``μ = 10``, ``γ = 120`` (their ``windowvariation.m`` weighs pairs by
  ``exp(−½‖(μ·L/100, γ·a/220, γ·b/220)‖²)``): at the paper's ``t = 0.05`` the weights are exactly
  Bi et al.'s, whose parameters the paper says it reuses. ``ΔL = 10`` or ``Δa ≈ 1.8`` gives a
  weight 0.61, ``ΔL = 30`` or ``Δa ≈ 5.5`` gives 0.011: 5–6× narrower than ``"wide"``. Texture
  and thin coloured prints survive the flattening (on a seeded Mondrian with 3% noise, Stage 2
  alone brings the RMSE from 0.030 to 0.012 with ``"bi"`` and to 0.021 with ``"wide"``).

Weights below ``e^MIN_EXPONENT`` (``e^-30 ≈ 1e-13``) are 0. Against the data term such a pair
changes nothing in float32 (its weight, squared in the ``z`` step, is ~1e-26 of the data
weight), but the squares and products of weights that small are subnormal numbers, which x86
CPUs process through a slow microcode path: on a 512×384 photo 0.6% of the 11×11 window's
weights lay between 1e-35 and 1e-18 and the 60-offset product took 10.5 ms instead of 5.6 ms.

Masks: a ``(B, 1, H, W)`` bool ``mask`` zeroes every pair touching a pixel outside it, so those
pixels keep only the data term; the solver then returns ``ρ`` there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import kornia
import torch

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors import kernels
from torchiid.priors.stencil import Stencil, shift_slices

__all__ = [
    "COLOUR_WEIGHTS",
    "lab_features",
    "stencil_affinity",
    "merged_stencil_affinity",
    "pair_affinity",
    "StencilL1Term",
    "PairL1Term",
    "BregmanStats",
    "REPLAY_STEPS",
    "MIN_EXPONENT",
    "data_term",
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
    device of ``colour``) receives the result instead of a new tensor.

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
    out = colour.new_zeros(shape) if out is None else out.zero_()
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


def data_term(z: torch.Tensor, rho: torch.Tensor, gamma_a: float = 1.0) -> torch.Tensor:
    """``γ_a ‖z − ρ‖²`` per image (Eq. 11). Shape: ``(B, C, H, W)`` twice -> ``(B,)``."""
    return gamma_a * (z - rho).square().flatten(1).sum(dim=1)


@dataclass(frozen=True)
class BregmanStats:
    """What one Bregman update measured, per image (``bregman_step(..., stats=True)``).

    For the duality gap and the residual balancing of
    :func:`~torchiid.solvers.split_bregman.split_bregman`: the update at ``z`` from ``b`` gives
    ``u = W M z + b``, ``b' = clamp(u, −λ, λ)`` and ``d = u − b'``.

    Attributes:
        l1: ``‖W M z‖₁`` ``(B,)``.
        primal: ``‖b' − b‖² = ‖W M z − d‖²`` (the squared primal residual) ``(B,)``.
        apply_sq: ``‖W M z‖²`` ``(B,)``.
        split_sq: ``‖d‖²`` ``(B,)``.
        adjoint: ``(W M)ᵀ b'`` ``(B, C, H, W)``; ``b' / λ`` is a feasible dual point.
    """

    l1: torch.Tensor
    primal: torch.Tensor
    apply_sq: torch.Tensor
    split_sq: torch.Tensor
    adjoint: torch.Tensor


def _sums(x: torch.Tensor) -> torch.Tensor:
    return x.flatten(1).sum(dim=1)


class _L1Term:
    """Shared Split-Bregman step for a weighted difference operator ``W M``.

    Subclasses provide ``apply`` (``W M z``), ``adjoint`` (``(W M)ᵀ y``), ``normal_matvec``
    (``Mᵀ W² M z``), ``normal_diagonal`` and ``init_state``.
    """

    #: ``bregman_step`` takes ``stats=True`` (:class:`BregmanStats`) and ``rescale_state``
    #: exists: Split-Bregman may stop on the duality gap and change its penalty
    bregman_stats = True

    def apply(self, z: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖W M z‖₁`` per image, shape ``(B,)``."""
        return self.apply(z).abs().flatten(1).sum(dim=1)

    def bregman_step(
        self,
        z: torch.Tensor,
        b: torch.Tensor | None,
        lam: float,
        with_l1: bool = True,
        stats: bool = False,
    ):
        """One Bregman update (Goldstein & Osher 2009) at ``z``.

        With ``u = W M z + b``: ``d = shrink(u, λ)``, ``b ← u − d = clamp(u, −λ, λ)`` (in place),
        and the right-hand side contribution ``(W M)ᵀ (d − b)`` of the next ``z`` step.
        ``b=None`` stands for the zero state of the first step; a new state is returned.

        Returns:
            ``(b, rhs (B, C, H, W), ‖W M z‖₁ (B,))``; the last is ``None`` unless ``with_l1``.
            With ``stats=True`` a fourth item, the update's :class:`BregmanStats`.
        """
        wz = self.apply(z)
        l1 = _sums(wz.abs()) if with_l1 or stats else None
        apply_sq = _sums(wz.square()) if stats else None
        old = b.clone() if stats and b is not None else None
        u = wz if b is None else wz.add_(b)
        b = u.clamp(-lam, lam) if b is None else b.copy_(u.clamp(-lam, lam))
        measured = None
        if stats:
            primal = _sums(b.square() if old is None else (b - old).square_())
            split_sq = _sums((u - b).square_())
            measured = BregmanStats(l1, primal, apply_sq, split_sq, self.adjoint(b))
        rhs = self.adjoint(u.sub_(b).sub_(b))
        return (b, rhs, l1, measured) if stats else (b, rhs, l1)

    def rescale_state(self, b: torch.Tensor | None, lam: float, new_lam: float):
        """The state ``b`` written at threshold ``lam`` for ``new_lam``: ``b · new_lam / lam``.

        Keeps the dual variable ``b / λ`` (Split-Bregman's penalty ``θ = γ / λ`` changes, the
        Lagrange multiplier ``θ b`` stays). In place; returns the state.
        """
        return None if b is None else b.mul_(new_lam / lam)


#: earlier updates a replayed Bregman state (:meth:`StencilL1Term.bregman_step`) recomputes
#: at most; a solve with more stores its state from then on
REPLAY_STEPS = 3


@dataclass(frozen=True)
class _Replay:
    """A Bregman state kept as the ``z`` of its updates (oldest first) and their ``λ``."""

    history: list[torch.Tensor]
    lam: float


class StencilL1Term(_L1Term):
    """``diag(v) M`` over a stencil's pairs, weights ``(B, K, H, W)`` (``A``, ``B``: Eqs. 8, 9).

    Args:
        stencil: the fixed-offset pairs.
        weights: pair weights ``v`` indexed by the first pixel; entries of pairs leaving the
            image are ignored (set to 0).
        zero_invalid: set those entries to 0 (a copy); ``False`` when they already are, as for
            :func:`stencil_affinity` and :func:`merged_stencil_affinity`, saves a pass.
        state: optional storage ``(B, C, K, H, W)`` for the Bregman variable of a solve that
            starts from the zero state (its contents are overwritten, never read); reusing one
            buffer across solves avoids faulting in fresh memory every time.
        warm: ``state`` holds a Bregman variable to start from (e.g. the previous solve's on
            the same image; entries of pairs leaving the image are never read): Split-Bregman
            then starts with the update ``b ← clamp(W M z + b, −λ, λ)`` from it instead of from
            the zero state (:attr:`initial_state`).
        keep_state: store the Bregman variable at every update, also the last one of a
            solve (needed when ``state`` is to warm-start a later solve). ``False``: the last
            update (``final=True``) leaves it unwritten, saving a write of ``C·K`` planes
            (141 MB at 512×384); :attr:`state_written` then tells that the storage is stale.
        replay: with ``keep_state=False``, keep the state as the ``z`` of its updates instead
            of storing it (see :meth:`bregman_step`); ``False`` for solves that make more
            than ``REPLAY_STEPS + 1`` updates, which would replay at a loss.
        state_step: with a ``torch.int16`` ``state`` and ``warm``, the step of its values
            (:attr:`state_step` of the solve that wrote it).

    Fixed-point state. A ``torch.int16`` ``state`` keeps the Bregman variable in 16-bit fixed
    point: each value of ``[−λ, λ]`` as an integer ``q`` in ``[−32767, 32767]``, read back as
    ``q · state_step`` with ``state_step = λ / 32767`` of the update that wrote it
    (:func:`~torchiid.priors.kernels.fixed_point_scales`; at most ``λ / 65534`` off). Half the
    memory and memory traffic of float32, for long solves (the ``converged`` preset's
    pipeline cache uses it). Each update computes in the image's dtype and rounds only what it
    stores; the compiled kernel and the torch ops round the same way, so they agree bitwise.
    """

    def __init__(
        self,
        stencil: Stencil,
        weights: torch.Tensor,
        *,
        zero_invalid: bool = True,
        state: torch.Tensor | None = None,
        warm: bool = False,
        keep_state: bool = True,
        replay: bool = True,
        state_step: float | None = None,
    ) -> None:
        if warm and state is None:
            raise ParameterError(
                "StencilL1Term(warm=True) needs state=, the Bregman variable to start from"
            )
        if state is not None and state.dtype == torch.int16:
            if warm and not (state_step is not None and state_step > 0):
                raise ParameterError(
                    "StencilL1Term(warm=True) with an int16 state needs state_step=, the step "
                    "of its values (the state_step of the solve that wrote it)"
                )
        elif state is not None and not state.is_floating_point():
            raise ParameterError(f"state must be floating point or torch.int16, got {state.dtype}")
        self.stencil = stencil
        if zero_invalid:
            weights = weights * stencil.valid.to(device=weights.device, dtype=weights.dtype)
        self.weights = weights
        self.state = state
        self.warm = warm
        self.keep_state = keep_state
        self.replay = replay
        self.state_written = False  # the last update stored its Bregman variable
        self.state_step = state_step  # the step of an int16 state's values

    @property
    def skips_final_state(self) -> bool:
        """Whether Split-Bregman may call the solve's last update with ``final=True``."""
        return not self.keep_state

    @property
    def initial_state(self) -> torch.Tensor | None:
        """The Bregman variable Split-Bregman starts from (``None``: the zero state)."""
        return self.state if self.warm else None

    def init_state(self, z: torch.Tensor) -> torch.Tensor:
        """Zero Bregman variable ``(B, C, K, H, W)``."""
        b, c, h, w = z.shape
        return z.new_zeros(b, c, self.stencil.num_offsets, h, w)

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``diag(v) M z``: ``(B, C, H, W) -> (B, C, K, H, W)`` (materialises; for reference)."""
        return self.weights.unsqueeze(1) * self.stencil.apply(z)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v) y``: ``(B, C, K, H, W) -> (B, C, H, W)``."""
        return self.stencil.adjoint(self.weights.unsqueeze(1) * y)

    def _loop(self):
        h, w = self.stencil.height, self.stencil.width
        for k, (dy, dx) in enumerate(self.stencil.offsets):
            yield k, shift_slices(dy, dx, h, w)

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖diag(v) M z‖₁`` per image ``(B,)`` without materialising ``M z``."""
        out = z.new_zeros(z.shape[0])
        for k, (yi, xi, yj, xj) in self._loop():
            d = (z[:, :, yi, xi] - z[:, :, yj, xj]).abs_().mul_(self.weights[:, k : k + 1, yi, xi])
            out += d.flatten(1).sum(dim=1)
        return out

    @cached_property
    def _degree(self) -> torch.Tensor:
        """Weighted degree ``Σ_j v²_ij`` over both directions of every pair, ``(B, 1, H, W)``."""
        if kernels.usable(self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_degree(self.weights, self.stencil.offsets, square=True)
        return self.stencil.laplacian_diagonal(self.weights.square(), zero_invalid=False)

    @cached_property
    def _w2(self) -> torch.Tensor:
        """The squared weights ``v²`` (only the torch product keeps them)."""
        return self.weights.square()

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v²) M z = deg ⊙ z − Σ_k v²_k ⊙ (shift_k(z) + shift_−k(z))``.

        Two fused in-place ``addcmul`` per offset, both reading the weight stored at the first
        pixel of the pair, so nothing of size ``(B, K, H, W)`` is built per call. On CPU
        tensors outside autograd the compiled one-pass kernel computes the same product, the
        weights squared on the fly (:func:`torchiid.priors.kernels.stencil_product`).

        Shape:
            ``(B, C, H, W) -> (B, C, H, W)``.
        """
        same_batch = z.shape[0] == self.weights.shape[0]  # else the torch ops broadcast
        if same_batch and kernels.usable(z, self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_product(z, self.weights, self.stencil.offsets, square=True)
        out = self._degree * z
        for k, (yi, xi, yj, xj) in self._loop():
            wk = self._w2[:, k : k + 1, yi, xi]
            out[:, :, yi, xi].addcmul_(z[:, :, yj, xj], wk, value=-1)
            out[:, :, yj, xj].addcmul_(z[:, :, yi, xi], wk, value=-1)
        return out

    def normal_diagonal(self) -> torch.Tensor:
        """Diagonal of ``Mᵀ diag(v²) M`` (the weighted degree), ``(B, 1, H, W)``."""
        return self._degree

    def bregman_step(
        self,
        z: torch.Tensor,
        b: torch.Tensor | _Replay | None,
        lam: float,
        with_l1: bool = True,
        final: bool = False,
        stats: bool = False,
    ):
        """Fused per-offset version of :meth:`_L1Term.bregman_step` (``b`` updated in place).

        The differences of each offset are written into one scratch buffer, so the loop
        allocates nothing; ``with_l1=False`` skips the objective's reduction (about a third of
        the time). With ``b=None`` (the zero state) the new state is allocated uninitialised:
        its entries for pairs leaving the image are unspecified and never read. With
        ``final=True`` and ``keep_state=False`` the new state is not stored: the clamped
        values go through a second scratch buffer and ``b`` is returned unchanged (``None``
        from the zero state).

        Replayed state. With ``keep_state=False`` on CPU (the compiled kernels, see
        :func:`~torchiid.priors.kernels.bregman_replay`) and ``with_l1=False``, a solve from
        the zero state keeps no ``(B, C, K, H, W)`` variable at all: the state passed between
        the calls is the list of the ``z`` it was updated at, and each update rebuilds every
        pair's variable from them, in the torch path's operations and order. Up to
        :data:`REPLAY_STEPS` earlier updates are replayed; a longer solve (or a call that
        needs the torch path) stores the state from then on. At the ``default`` preset's two
        updates per solve this saves writing and reading 141 MB per alternation at 512×384
        (measured: 18–19 ms per update against 26–28 ms).

        Stored state. Otherwise, on the same compiled path, the update reads and writes the
        stored state in one pass (:func:`~torchiid.priors.kernels.bregman_update`; the torch
        ops, kept for GPUs, autograd and ``with_l1=True``, make about ten per offset). A
        ``torch.int16`` state (see the class notes) halves what that pass moves: 19.0 ms
        against 26.2 ms per update at 512×384 on 2 threads.

        ``stats=True`` also returns the update's :class:`BregmanStats` (a fourth item), from
        the same pass on the compiled path (``kernels.bregman_update(stats=True)``).
        """
        replayable = (
            not self.keep_state
            and self.replay
            and not with_l1
            and not stats
            and (b is None or isinstance(b, _Replay))
            and z.shape[0] == self.weights.shape[0]
            and kernels.usable(z, self.weights, offsets=self.stencil.offsets)
        )
        if replayable:
            history = [] if b is None else b.history
            if len(history) <= REPLAY_STEPS and (b is None or b.lam == lam):
                self.state_written = False
                rhs = kernels.bregman_replay(history, z, self.weights, self.stencil.offsets, lam)
                if final:
                    return b, rhs, None
                return _Replay([*history, z.clone()], lam), rhs, None
        compiled = (
            not with_l1
            and z.shape[0] == self.weights.shape[0]
            and kernels.usable(z, self.weights, offsets=self.stencil.offsets)
        )
        if isinstance(b, _Replay):
            b = self._materialise(b, compiled)
        state_ok = b is None or (
            b.is_contiguous()
            and (kernels.usable(z, b) or (b.dtype == torch.int16 and b.device.type == "cpu"))
        )
        if compiled and state_ok:
            # the stored state in one compiled pass (the torch path makes ~10 per offset)
            store = not (final and not self.keep_state)
            self.state_written = store
            fresh = b is None
            if store and fresh:
                b = self._state_storage(z)
            out = kernels.bregman_update(
                z, self.weights, self.stencil.offsets, lam, state=b, read=not fresh,
                write=store, state_step=self.state_step or 1.0, stats=stats,
            )  # fmt: skip
            if store and b.dtype == torch.int16:
                self.state_step = kernels.fixed_point_scales(lam)[0]
            if not stats:
                return b, out, None
            rhs, adj, sums = out
            sums = sums.to(z.dtype).unbind(1)
            return b, rhs, sums[0], BregmanStats(sums[0], sums[1], sums[2], sums[3], adj)
        return self._torch_step(z, b, lam, with_l1, final, stats=stats)

    def rescale_state(self, b, lam: float, new_lam: float):
        """:meth:`_L1Term.rescale_state`; an int16 state only changes its step (no pass)."""
        if isinstance(b, _Replay):
            compiled = kernels.usable(b.history[-1], self.weights, offsets=self.stencil.offsets)
            b = self._materialise(b, compiled)
        if b is not None and b.dtype == torch.int16:
            # q = b / λ · 32767 is the dual variable: read it with the step of the new λ
            self.state_step = kernels.fixed_point_scales(new_lam)[0]
            return b
        return super().rescale_state(b, lam, new_lam)

    def _state_storage(self, z: torch.Tensor) -> torch.Tensor:
        """Storage ``(B, C, K, H, W)`` for a fresh state: ``state`` when it fits, else new."""
        bsz, c, h, w = z.shape
        shape = (bsz, c, self.stencil.num_offsets, h, w)
        st = self.state
        fits = st is not None and st.shape == shape and st.device == z.device
        if fits and st.dtype in (z.dtype, torch.int16):
            return st
        return z.new_empty(shape)

    def _materialise(self, replay: _Replay, compiled: bool) -> torch.Tensor:
        """The stored Bregman variable of a replayed state (its updates run again)."""
        *earlier, last = replay.history
        storage = self._state_storage(last)
        fixed = storage.dtype == torch.int16
        if fixed:  # replayed in the image's dtype, like the kernel, and rounded once
            self.state_step = kernels.fixed_point_scales(replay.lam)[0]
        if compiled:
            kernels.bregman_update(
                last, self.weights, self.stencil.offsets, replay.lam,
                state=storage, write=True, history=earlier,
            )  # fmt: skip
            return storage
        b = None
        for zs in replay.history:
            b, _, _ = self._torch_step(zs, b, replay.lam, False, False, float_state=fixed)
        if fixed:
            storage.copy_(b.mul_(kernels.fixed_point_scales(replay.lam)[1]).round_())
            return storage
        return b

    def _torch_step(
        self,
        z: torch.Tensor,
        b: torch.Tensor | None,
        lam: float,
        with_l1: bool,
        final: bool,
        float_state: bool = False,
        stats: bool = False,
    ):
        rhs = torch.zeros_like(z)
        scratch = torch.empty_like(z)
        l1 = z.new_zeros(z.shape[0]) if with_l1 or stats else None
        if stats:
            sums = z.new_zeros(3, z.shape[0])  # ‖b' − b‖², ‖W M z‖², ‖d‖²
            adj = torch.zeros_like(z)
        fresh = b is None
        store = not (final and not self.keep_state)
        self.state_written = store
        if fresh and store:
            b = z.new_empty(self.init_state(z).shape) if float_state else self._state_storage(z)
        fixed = b is not None and b.dtype == torch.int16
        step_in = self.state_step
        step_out, inv_out = kernels.fixed_point_scales(lam) if fixed else (None, None)
        if not store or fixed:
            clamped = torch.empty_like(z)
        for k, (yi, xi, yj, xj) in self._loop():
            wk = self.weights[:, k : k + 1, yi, xi]
            u = torch.sub(z[:, :, yi, xi], z[:, :, yj, xj], out=scratch[:, :, yi, xi]).mul_(wk)
            if l1 is not None:
                l1 += u.abs().flatten(1).sum(dim=1)
            if stats:
                sums[1] += _sums(u.square())
            old = None
            if not fresh:
                bk = b[:, :, k, yi, xi]
                old = bk.to(z.dtype).mul_(step_in) if fixed else bk
                if stats and old is bk:
                    old = bk.clone()  # the new b overwrites it
                u += old
            # the new b, written straight into the state (or into scratch when not kept or
            # stored in fixed point)
            bk = b[:, :, k, yi, xi] if store and not fixed else clamped[:, :, yi, xi]
            torch.clamp(u, -lam, lam, out=bk)
            if stats:
                sums[0] += _sums(bk.square() if old is None else (bk - old).square_())
                sums[2] += _sums((u - bk).square_())
                adj[:, :, yi, xi].addcmul_(bk, wk)
                adj[:, :, yj, xj].addcmul_(bk, wk, value=-1)
            if store and fixed:
                b[:, :, k, yi, xi] = bk.mul(inv_out).round_()
            e = u.sub_(bk, alpha=2.0)  # d - b; (W M)^T scatters w * (d - b) to i and j
            rhs[:, :, yi, xi].addcmul_(e, wk)
            rhs[:, :, yj, xj].addcmul_(e, wk, value=-1)
        if store and fixed:
            self.state_step = step_out
        if stats:
            return b, rhs, l1, BregmanStats(l1, sums[0], sums[1], sums[2], adj)
        return b, rhs, l1

    def matrix(self) -> torch.Tensor:
        """``diag(v) M`` as sparse COO ``(B·P, B·H·W)`` acting on one channel."""
        return self.stencil.difference_matrix(self.weights.square())


class PairL1Term(_L1Term):
    """``diag(v) M`` over an explicit pair list per image (``C``: Eq. 10).

    Args:
        i: first pixel of each pair, flat index ``y·W + x`` within its image.
        j: second pixel of each pair.
        weights: pair weights; padding pairs carry weight 0.
        height: image height ``H``.
        width: image width ``W``.

    Shape:
        ``i``, ``j``, ``weights``: ``(B, P)``.
    """

    def __init__(
        self, i: torch.Tensor, j: torch.Tensor, weights: torch.Tensor, height: int, width: int
    ) -> None:
        if not (i.shape == j.shape == weights.shape) or i.dim() != 2:
            raise ParameterError(
                f"expected i, j, weights of one shape (B, P), got {tuple(i.shape)}, "
                f"{tuple(j.shape)}, {tuple(weights.shape)}"
            )
        self.i, self.j, self.weights = i, j, weights
        self.height, self.width = int(height), int(width)

    def init_state(self, z: torch.Tensor) -> torch.Tensor:
        """Zero Bregman variable ``(B, C, P)``."""
        return z.new_zeros(z.shape[0], z.shape[1], self.i.shape[1])

    def _idx(self, idx: torch.Tensor, c: int) -> torch.Tensor:
        return idx.unsqueeze(1).expand(idx.shape[0], c, idx.shape[1])

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``diag(v) M z``: ``(B, C, H, W) -> (B, C, P)``."""
        b, c = z.shape[:2]
        zf = z.reshape(b, c, -1)
        d = zf.gather(2, self._idx(self.i, c)) - zf.gather(2, self._idx(self.j, c))
        return d * self.weights.unsqueeze(1)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v) y``: ``(B, C, P) -> (B, C, H, W)``."""
        b, c = y.shape[:2]
        wy = y * self.weights.unsqueeze(1)
        out = y.new_zeros(b, c, self.height * self.width)
        out.scatter_add_(2, self._idx(self.i, c), wy).scatter_add_(2, self._idx(self.j, c), -wy)
        return out.view(b, c, self.height, self.width)

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v²) M z``, ``(B, C, H, W) -> (B, C, H, W)``."""
        return self.adjoint(self.apply(z))

    def normal_diagonal(self) -> torch.Tensor:
        """Diagonal of ``Mᵀ diag(v²) M``, ``(B, 1, H, W)``."""
        w2 = self.weights.square()
        out = w2.new_zeros(w2.shape[0], self.height * self.width)
        out.scatter_add_(1, self.i, w2).scatter_add_(1, self.j, w2)
        return out.view(-1, 1, self.height, self.width)

    def matrix(self) -> torch.Tensor:
        """``diag(v) M`` as sparse COO ``(B·P, B·H·W)`` acting on one channel."""
        b, p = self.i.shape
        n = self.height * self.width
        dev = self.i.device
        rows = torch.arange(b * p, device=dev)
        off = (torch.arange(b, device=dev) * n).view(-1, 1)
        idx = torch.stack(
            [
                torch.cat([rows, rows]),
                torch.cat([(self.i + off).reshape(-1), (self.j + off).reshape(-1)]),
            ]
        )
        val = torch.cat([self.weights.reshape(-1), -self.weights.reshape(-1)])
        return torch.sparse_coo_tensor(idx, val, (b * p, b * n), check_invariants=False).coalesce()
