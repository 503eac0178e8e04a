"""Stage 2: the L1 reflectance formulation (paper §3.3–3.4, Eqs. 6–13).

Given the intermediate reflectance ``ρ = I / σ`` of the shading stage, solve

    π(z) = γ_l ‖A z‖₁ + γ_m ‖B z‖₁ + γ_g ‖C z‖₁ + γ_a ‖z − ρ‖²

by Split-Bregman (:func:`~torchiid.solvers.split_bregman.split_bregman`). All weights are
recomputed from ``ρ`` at every call (the paper re-estimates priors each iteration):

- ``A`` (local, Eq. 8): pairs of an 11×11 window, ``v^l = exp(−‖Δr̄‖²/2t²)``;
- ``B`` (mid-level, Eq. 9): same pairs, ``v^m = v^l · exp(−‖Δg̊‖²/2t_g²)`` on the PCA-reduced
  proposal features ``g̊``;
- ``C`` (global, Eq. 10): all pairs of representative pixels (one per segment).

``A`` and ``B`` share their pairs, so ``γ_l‖diag(v^l)Mz‖₁ + γ_m‖diag(v^m)Mz‖₁`` equals
``(γ_l+γ_m)‖diag(v̂)Mz‖₁`` with ``v̂ = (γ_l v^l + γ_m v^m)/(γ_l+γ_m)`` exactly (same pairs,
non-negative weights, anisotropic L1). With ``merge_stencil_terms=True`` (default) the solver
works on this single term, which halves time and memory; the minimiser is unchanged (the
Bregman splitting, hence the iterates after few iterations, differ slightly).

Video. A :class:`~torchiid.stages.config.TemporalPrior` in the problem adds a term ``"T"``
pulling ``z`` toward another frame's reflectance warped onto this one (:func:`temporal_term`):
an L1 term ``γ_T ‖c ⊙ (z − κT)‖₁`` solved by Split-Bregman like the others
(:class:`TemporalL1Term`), or a quadratic anchor ``γ_T ‖√c ⊙ (z − κT)‖²`` that enters the
``z`` step's normal equations exactly (:class:`TemporalAnchorTerm`). Without it (still
images) nothing changes.

Scales. The paper's values (γ_l = γ_m = 20, γ_g = 2, θ = 40, §4) are reused from Bi et al.'s
Matlab code, which works on 8-bit values ``0..255``. ``γ_a`` is not given; 1 is used. We evaluate
Eq. 12 on ``s·z`` (``s = value_scale = 255``) and divide by ``s``, i.e. on our ``[0, 1]`` linear
values the solver minimises ``Σ_k γ_k ‖W_k M_k z‖₁ + s·γ_a ‖z − ρ‖²`` with penalty ``s·θ``. With
``s = 1`` the L1 terms dominate (γ_l · 120 neighbours against a data weight of 1) and the
minimiser collapses colour edges. Measured on a seeded 64×48 Mondrian with ``ρ`` = reflectance +
N(0, 0.03²) (RMSE of ``ρ`` to the truth 0.030): converged solutions (30 outer × 30 CG) reach
RMSE 0.13 at ``s = 1`` and 0.064 at ``s = 255``; the default few iterations (3 outer × 5 CG,
``s = 255``) reach 0.021. The suppressed luminance (``w_L = 0.1``) lets the exact minimiser
merge patches differing mainly in lightness (0.026 converged with ``w_L = 1``): the flattening
behaviour of Bi et al.; the few-iteration default stops well before that (figures for
``colour_weights="wide"``).

Colour-weight width and the ablation (MIT-Berkeley, 10 objects). ``B``'s weights are ``v^l``
times a gate, on ``A``'s pairs, so ``B`` can only add flattening where ``A`` flattens; on
``g̊`` the gate (``t_g = t = 0.05``) is in effect a same-atom indicator (pairs inside one atom
have ``Δg̊ = 0``, pairs across atoms ``‖Δg̊‖ ≈ 0.3``). With the ``"wide"`` weights ``A``
alone already washes out thin coloured prints and ``B`` makes it worse (mean LMSE, 4 × 5
Bregman steps: v7 0.0239, v4 0.0224, v4 with ``γ_l = 40`` 0.0234); with ``"bi"`` (Bi et al.'s
weights, the default) ``A`` keeps them and ``B`` helps (v7 0.0230, v4 0.0248, v4 with
``γ_l = 40`` 0.0235, v1 0.0406; these figures with the shading PCG capped at 100 iterations and
4 × 5 Bregman steps; with the ``default`` preset's 2 × 3 steps and warm cap 30: v7 0.0222, v4
0.0225, v1 0.0416; ``paper`` preset: v7 0.0246, v4 0.0259).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import kornia
import torch

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_image, check_same_batch, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors import kernels
from torchiid.priors.reflectance_terms import (
    COLOUR_WEIGHTS,
    REPLAY_STEPS,
    StencilL1Term,
    lab_features,
    merged_stencil_affinity,
    stencil_affinity,
)
from torchiid.priors.representatives import (
    SegmentLayout,
    global_pair_term,
    representative_pixels,
    segment_layout,
)
from torchiid.priors.stencil import Stencil
from torchiid.solvers.split_bregman import SplitBregmanResult, split_bregman
from torchiid.stages.config import (
    ReflectanceOptions,
    ReflectanceProblem,
    ReflectanceWeights,
    TemporalPrior,
)

__all__ = [
    "ReflectanceCache",
    "ReflectanceTimings",
    "ReflectanceResult",
    "ReflectanceTerms",
    "build_reflectance_terms",
    "solve_reflectance",
    "shading_from_ratio",
    "TemporalL1Term",
    "TemporalAnchorTerm",
    "temporal_term",
]

logger = logging.getLogger(__name__)


@dataclass
class ReflectanceCache:
    """Parts of Eq. 12 that do not change between the alternations on one image.

    The proposal-feature factor ``exp(−‖Δg̊‖²/2t_g²)`` of ``B``'s weights (Eq. 9) depends only
    on Stage 0's ``g̊`` and the mask, not on the current ``ρ``, so the pipeline computes it once
    per image batch and reuses it; it is recomputed when its inputs (same tensors, unmodified)
    or parameters differ. It also keeps the storage of the Bregman variable (``(B, 3, K, H, W)``,
    the stage's largest tensor, in 16-bit fixed point: see
    :class:`~torchiid.priors.reflectance_terms.StencilL1Term`) and of the merged ``A``/``B``
    weights, so that later alternations write into memory already in use.

    Attributes:
        semantic: (key of the inputs, ``(B, K, H, W)`` factor) or ``None``.
        layout: (key of the segments and mask, their
            :class:`~torchiid.priors.representatives.SegmentLayout`) for ``C``'s
            representatives, or ``None``.
        hits: how many computations were skipped.
        state_valid: the storage holds the last solve's Bregman variable of the local term
            (what ``ReflectanceOptions.warm_state`` starts the next solve from).
        state_step: the step of that variable's fixed-point values.
        theta: the Split-Bregman penalty that variable was written at (it changes with
            ``ReflectanceOptions.theta_floor``; the next warm solve starts there).
    """

    semantic: tuple[InputKey, torch.Tensor] | None = None
    layout: tuple[InputKey, SegmentLayout] | None = None
    hits: int = 0
    state_valid: bool = False
    state_step: float | None = None
    theta: float | None = None
    _state: torch.Tensor | None = None
    _weights: torch.Tensor | None = None

    def reuse(self, slot: str, key: InputKey, compute: Callable[[], Any]) -> Any:
        """The value kept in ``slot`` if it was made from the inputs ``key``, else ``compute()``.

        ``slot`` is ``"semantic"`` or ``"layout"``; a computed value is kept there (with
        ``key``) for the next call, and every reuse counts in :attr:`hits`.
        """
        kept = getattr(self, slot)
        if kept is not None and kept[0] == key:
            self.hits += 1
            return kept[1]
        value = compute()
        setattr(self, slot, (key, value))
        return value

    def state_buffer(
        self, like: torch.Tensor, num_offsets: int, fixed_point: bool = True
    ) -> torch.Tensor:
        """Storage ``(B, C, K, H, W)`` for the Bregman variable, reused across calls.

        ``torch.int16`` (16-bit fixed point) by default; ``like``'s dtype with
        ``fixed_point=False`` (thresholds too small for it, see
        :func:`~torchiid.priors.kernels.fixed_point_fits`).
        """
        b, c, h, w = like.shape
        shape = (b, c, num_offsets, h, w)
        dtype = torch.int16 if fixed_point else like.dtype
        st = self._state
        if st is None or st.shape != shape or st.dtype != dtype or st.device != like.device:
            self._state = st = like.new_empty(shape, dtype=dtype)
            self.state_valid = False
        return st

    def weights_buffer(self, like: torch.Tensor, num_offsets: int) -> torch.Tensor:
        """Storage ``(B, K, H, W)`` for the merged ``A``/``B`` weights, reused across calls.

        Each alternation's weights replace the last one's (whose solve is over), so the
        pages of this 47 MB tensor (at 512×384) are faulted in once per image, not once per
        alternation.
        """
        b, _, h, w = like.shape
        shape = (b, num_offsets, h, w)
        buf = self._weights
        if (
            buf is None
            or buf.shape != shape
            or buf.dtype != like.dtype
            or buf.device != like.device
        ):
            self._weights = buf = like.new_empty(shape)
        return buf


@dataclass(frozen=True)
class ReflectanceTimings:
    """Wall-clock seconds spent in the stage (CPU timers; CUDA work is asynchronous).

    Attributes:
        features: colour features ``r̄`` (CIELab).
        weights_local: building ``v^l`` (or the merged ``A``/``B`` weights).
        weights_mid: ``B``'s proposal-feature factor (near 0 when taken from the cache).
        weights_global: representatives and ``v^g``.
        solve: Split-Bregman.
    """

    features: float
    weights_local: float
    weights_mid: float
    weights_global: float
    solve: float


@dataclass(frozen=True)
class ReflectanceResult:
    """Output of :func:`solve_reflectance`; linear RGB.

    Attributes:
        reflectance: ``R = z`` clamped at 0, ``(B, 3, H, W)``; equals ``ρ`` outside ``mask``.
        shading: ``S = Σ_c I_c / Σ_c R_c`` (:func:`shading_from_ratio`), ``(B, 1, H, W)``.
            ``I = R·S`` holds only approximately; the pipeline restores it exactly by
            ``R = I / S``.
        solver: the Split-Bregman diagnostics.
        num_representatives: ``(B,)`` size of ``Q`` (0 when ``C`` is off).
        timings: :class:`ReflectanceTimings`.
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    solver: SplitBregmanResult
    num_representatives: torch.Tensor
    timings: ReflectanceTimings


def shading_from_ratio(
    image: torch.Tensor, reflectance: torch.Tensor, eps: float = 1e-4
) -> torch.Tensor:
    """Gray shading ``S = Σ_c I_c / max(Σ_c R_c, eps)``.

    The ratio of channel sums is the least-squares gray ``S`` for ``I ≈ R·S`` weighted towards the
    brighter channels and is stable where one channel of ``R`` is near 0.

    Shape:
        ``(B, 3, H, W)`` twice -> ``(B, 1, H, W)``.
    """
    return image.sum(dim=1, keepdim=True) / reflectance.sum(dim=1, keepdim=True).clamp_min(eps)


@dataclass(frozen=True)
class ReflectanceTerms:
    """Eq. 12's sparsity priors as built by :func:`build_reflectance_terms`.

    Attributes:
        terms: name -> ``(gamma, term)`` of every active L1 term, in solver order: ``"A+B"``
            (the merged local and mid-level term) or ``"A"`` and ``"B"``, then ``"C"``, then
            the temporal term ``"T"`` when the problem has a ``temporal`` prior.
        num_representatives: ``(B,)`` size of ``Q`` (0 when ``C`` is off).
        timings: seconds for the colour features, ``A``'s, ``B``'s and ``C``'s weights.
    """

    terms: dict[str, tuple[float, object]]
    num_representatives: torch.Tensor
    timings: tuple[float, float, float, float]


def _check_problem(problem: ReflectanceProblem) -> None:
    rho, image, mask = problem.rho, problem.image, problem.mask
    check_image(rho, "rho")
    check_image(image, "image")
    check_same_batch(rho, image, names=["rho", "image"])
    b, _, h, w = rho.shape
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        if mask.dtype != torch.bool:
            raise ShapeError(f"expected a bool mask, got {mask.dtype}")
    if problem.gpca is not None:
        check_shape(problem.gpca, (b, "d", h, w), "gpca")
        check_finite(problem.gpca, "gpca")
    if problem.segments is not None:
        check_shape(problem.segments, (b, h, w), "segments")
    if problem.temporal is not None:
        check_shape(problem.temporal.target, (b, 3, h, w), "temporal target")
        check_finite(problem.temporal.target, "temporal target")
        check_shape(problem.temporal.confidence, (b, 1, h, w), "temporal confidence")
        check_finite(problem.temporal.confidence, "temporal confidence")


def build_reflectance_terms(
    problem: ReflectanceProblem,
    weights: ReflectanceWeights,
    options: ReflectanceOptions,
    cache: ReflectanceCache | None = None,
) -> ReflectanceTerms:
    """Build the sparsity priors of Eq. 12: the one place ``A``, ``B`` and ``C`` are made.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ReflectanceProblem`); ``B`` needs
            ``gpca`` and ``C`` needs ``segments``.
        weights: :class:`~torchiid.stages.config.ReflectanceWeights`, 0 is off.
        options: :class:`~torchiid.stages.config.ReflectanceOptions`.
        cache: reuse ``B``'s proposal-feature factor and the Bregman-state storage.

    Returns:
        :class:`ReflectanceTerms`.
    """
    _check_problem(problem)
    o = options
    if o.colour_weights not in COLOUR_WEIGHTS:
        raise ParameterError(
            f"colour_weights must be one of {', '.join(COLOUR_WEIGHTS)}, got {o.colour_weights!r}"
        )
    rho, mask, gpca = problem.rho.contiguous(), problem.mask, problem.gpca
    b, _, h, w = rho.shape
    use_a = weights.gamma_l > 0
    use_b = weights.gamma_m > 0 and gpca is not None
    if weights.gamma_m > 0 and gpca is None:
        logger.debug("gamma_m > 0 but no gpca given: mid-level term B is off")
    use_c = weights.gamma_g > 0 and problem.segments is not None
    stencil = Stencil.square(h, w, o.window, device=rho.device)
    t0 = time.perf_counter()
    w_l, lab_scale = COLOUR_WEIGHTS[o.colour_weights]
    lum = w_l if o.luminance_weight is None else o.luminance_weight
    rbar = lab_features(rho, luminance_weight=lum, lab_scale=lab_scale)
    t1 = time.perf_counter()
    terms: dict[str, tuple[float, object]] = {}
    t_m = o.t_g or o.t
    e_g = None
    if use_b:

        def factor() -> torch.Tensor:
            return stencil_affinity(gpca.to(rho.dtype), stencil, t_m, mask)

        if cache is None:
            e_g = factor()
        else:
            e_g = cache.reuse("semantic", input_key(gpca, t_m, mask, rho.dtype, o.window), factor)
    t2 = time.perf_counter()
    if use_a and use_b and o.merge_stencil_terms:
        gl, gm = weights.gamma_l, weights.gamma_m
        out = None if cache is None else cache.weights_buffer(rho, stencil.num_offsets)
        merged = merged_stencil_affinity(rbar, e_g, stencil, o.t, gl, gm, mask, out=out)
        # 16-bit fixed point unless λ = γ / θ is too small for it (float32, as before, then)
        fixed = kernels.fixed_point_fits(float(gl + gm) / (o.theta * o.value_scale))
        state = None
        if cache is not None:
            state = cache.state_buffer(rho, stencil.num_offsets, fixed_point=fixed)
        warm = o.warm_state and cache is not None and cache.state_valid
        terms["A+B"] = (
            float(gl + gm),
            StencilL1Term(
                stencil,
                merged,
                zero_invalid=False,
                state=state,
                warm=warm,
                state_step=cache.state_step if warm else None,
                # only a later warm start reads the last update's state
                keep_state=o.warm_state and cache is not None,
                replay=o.max_outer <= REPLAY_STEPS + 1,  # every update's history short enough
            ),
        )
        if cache is not None:
            cache.state_valid = False  # valid again once the solve has written it
    elif use_a or use_b:
        v_l = stencil_affinity(rbar, stencil, o.t, mask)
        if use_a:
            terms["A"] = (float(weights.gamma_l), StencilL1Term(stencil, v_l, zero_invalid=False))
        if use_b:
            term = StencilL1Term(stencil, e_g * v_l, zero_invalid=False)
            terms["B"] = (float(weights.gamma_m), term)
    t3 = time.perf_counter()
    nrep = torch.zeros(b, dtype=torch.long, device=rho.device)
    if use_c:
        layout = None
        if cache is not None:
            key = input_key(problem.segments, mask)
            layout = cache.reuse("layout", key, lambda: segment_layout(problem.segments, mask))
        reps = representative_pixels(rbar, problem.segments, mask, layout=layout)
        terms["C"] = (float(weights.gamma_g), global_pair_term(rbar, reps, o.t))
        nrep = reps.counts
    if problem.temporal is not None:
        term = temporal_term(problem.temporal, rho, weights, options, mask)
        if term is not None:
            terms["T"] = term
    t4 = time.perf_counter()
    return ReflectanceTerms(terms, nrep, (t1 - t0, t3 - t2, t2 - t1, t4 - t3))


def solve_reflectance(
    problem: ReflectanceProblem,
    weights: ReflectanceWeights,
    options: ReflectanceOptions,
    *,
    z0: torch.Tensor | None = None,
    cache: ReflectanceCache | None = None,
) -> ReflectanceResult:
    """Reflectance formulation (Eq. 12) solved by Split-Bregman.

    Args:
        problem: ``ρ`` (the Stage 1 reflectance), the image, ``g̊`` for ``B``, the segments
            for ``C`` and the mask (:class:`~torchiid.stages.config.ReflectanceProblem`);
            pairs touching pixels outside the mask are dropped and ``R = ρ`` there.
        weights: :class:`~torchiid.stages.config.ReflectanceWeights` (``γ_l``, ``γ_m``,
            ``γ_g``: 0 is off; ``γ_a`` of the data term).
        options: :class:`~torchiid.stages.config.ReflectanceOptions`: the priors' constants
            and the Split-Bregman settings.
        z0: warm start (default ``ρ``), e.g. the previous alternation's ``R``.
        cache: reuse ``B``'s proposal-feature factor across calls on the same ``g̊``
            (:class:`ReflectanceCache`) and its Bregman-state storage.

    Returns:
        :class:`ReflectanceResult`.

    Shape:
        rho, image, z0 ``(B, 3, H, W)``; gpca ``(B, d, H, W)``; segments ``(B, H, W)`` long;
        mask ``(B, 1, H, W)`` bool.
    """
    o = options
    theta = o.theta * o.value_scale
    balanced = o.gap_tol > 0 and o.theta_floor < 1
    warm_theta = None
    if balanced and o.warm_state and cache is not None and cache.state_valid:
        warm_theta = cache.theta  # read before the terms are built (that clears state_valid)
    built = build_reflectance_terms(problem, weights, options, cache)
    if warm_theta is not None and "T" not in built.terms:
        # the warm state's multipliers θ b were reached at this penalty: go on from it (not
        # with a temporal term, whose anchor coefficient 2γ/θ is made for the options' θ and
        # which keeps θ fixed: it measures no gap)
        theta = min(max(warm_theta, theta * o.theta_floor), theta)
    # Channels-last inputs (e.g. a permuted HxWx3 array) make every per-offset slice op
    # stride over interleaved channels, about 5x slower: work on contiguous planes.
    rho, image, mask = problem.rho.contiguous(), problem.image.contiguous(), problem.mask
    z0 = None if z0 is None else z0.contiguous()
    t4 = time.perf_counter()
    sol = split_bregman(
        rho,
        [term for _, term in built.terms.values()],
        [gamma for gamma, _ in built.terms.values()],
        gamma_a=weights.gamma_a * o.value_scale,
        theta=theta,
        z0=z0,
        tol=o.tol,
        max_outer=o.max_outer,
        cg_tol=o.cg_tol,
        cg_max_iter=o.cg_max_iter,
        track_objective=o.track_objective,
        gap_tol=o.gap_tol or None,
        theta_range=(
            (o.theta * o.value_scale * o.theta_floor, o.theta * o.value_scale) if balanced else None
        ),
    )
    t5 = time.perf_counter()
    if cache is not None and "A+B" in built.terms and sol.outer_iterations.max() > 0:
        local = built.terms["A+B"][1]
        cache.state_valid = local.state_written
        cache.state_step = local.state_step
        cache.theta = sol.theta
    refl = sol.z.clamp_min(0.0)
    if mask is not None:
        refl = torch.where(mask, refl, rho)
    shading = shading_from_ratio(image, refl, o.eps)
    t_feat, t_local, t_mid, t_global = built.timings
    timings = ReflectanceTimings(t_feat, t_local, t_mid, t_global, t5 - t4)
    return ReflectanceResult(refl, shading, sol, built.num_representatives, timings)


class TemporalL1Term:
    """``‖diag(c) (z − T)‖₁``: an L1 pull toward a target, for Split-Bregman.

    An affine operator ``D z = c ⊙ (z − T)``: the Bregman step shrinks ``u = D z + b`` like
    the difference terms do, and the ``z`` step's right-hand side gets ``c ⊙ (d − b) + c² T``
    (from ``θ/2 ‖d − c(z − T) − b‖²``), its normal matrix ``diag(c²)``.

    Args:
        target: ``(B, C, H, W)`` the target ``T``.
        confidence: ``(B, 1, H, W)`` per-pixel weights ``c >= 0``.
    """

    def __init__(self, target: torch.Tensor, confidence: torch.Tensor) -> None:
        self.target = target.contiguous()
        self.confidence = confidence.contiguous()
        self._c2 = self.confidence.square()
        self._c2t = self._c2 * self.target

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``c ⊙ (z − T)``, shape of ``z``."""
        return (z - self.target).mul_(self.confidence)

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖c ⊙ (z − T)‖₁`` per image ``(B,)``."""
        return self.apply(z).abs_().flatten(1).sum(dim=1)

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``c² ⊙ z`` (a fresh tensor)."""
        return self._c2 * z

    def normal_diagonal(self) -> torch.Tensor:
        """``c²``, ``(B, 1, H, W)``."""
        return self._c2

    def bregman_step(
        self, z: torch.Tensor, b: torch.Tensor | None, lam: float, with_l1: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One Bregman update at ``z``: ``(b, rhs, ‖D z‖₁)`` (see the class notes)."""
        u = self.apply(z)
        l1 = u.abs().flatten(1).sum(dim=1) if with_l1 else None
        if b is not None:
            u += b
        b = u.clamp(-lam, lam) if b is None else b.copy_(u.clamp(-lam, lam))
        rhs = u.sub_(b, alpha=2.0).mul_(self.confidence).add_(self._c2t)
        return b, rhs, l1


class TemporalAnchorTerm:
    """``Σ c ‖z − T‖²``: a quadratic pull toward a target, in Split-Bregman's term interface.

    Quadratic, so it needs no splitting: it adds ``2γ c`` to the ``z`` step's normal matrix
    and ``2γ c T`` to its right-hand side, exactly. The solver multiplies every term's normal
    product and right-hand side by its penalty ``θ``, so this term carries
    ``coefficient = 2γ / θ``; its "L1 norm" (used for the objective as ``γ · l1``) is the
    quadratic energy ``Σ c ‖z − T‖²``.

    Args:
        target: ``(B, C, H, W)`` the target ``T``.
        confidence: ``(B, 1, H, W)`` per-pixel weights ``c >= 0``.
        coefficient: ``2γ / θ`` of the solve it enters.
    """

    def __init__(self, target: torch.Tensor, confidence: torch.Tensor, coefficient: float):
        self.target = target.contiguous()
        self.confidence = confidence.contiguous()
        self._w = self.confidence * coefficient
        self._rhs = self._w * self.target

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """The energy ``Σ c ‖z − T‖²`` per image ``(B,)`` (see the class notes)."""
        return (z - self.target).square_().mul_(self.confidence).flatten(1).sum(dim=1)

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``(2γ/θ) c ⊙ z`` (a fresh tensor)."""
        return self._w * z

    def normal_diagonal(self) -> torch.Tensor:
        """``(2γ/θ) c``, ``(B, 1, H, W)``."""
        return self._w

    def bregman_step(
        self, z: torch.Tensor, b: torch.Tensor | None, lam: float, with_l1: bool = True
    ) -> tuple[None, torch.Tensor, torch.Tensor | None]:
        """No splitting: the state stays empty and the right-hand side is ``(2γ/θ) c T``."""
        return None, self._rhs, self.l1(z) if with_l1 else None


def temporal_term(
    prior: TemporalPrior,
    rho: torch.Tensor,
    weights: ReflectanceWeights,
    options: ReflectanceOptions,
    mask: torch.Tensor | None = None,
) -> tuple[float, TemporalL1Term | TemporalAnchorTerm] | None:
    """The temporal term ``"T"`` of a :class:`~torchiid.stages.config.TemporalPrior`.

    The target is brought to the scale of ``ρ`` on the trusted pixels (confidence > 0.5,
    inside the mask, ``Σ_c T > 1e-3``, ``Σ_c ρ > 1e-3``): with ``prior.sigma == 0`` by one
    factor per image, ``κ``, the median of ``Σ_c ρ / Σ_c T``; with ``prior.sigma > 0`` the
    target becomes ``ρ · exp(G_σ ∗ log(Σ_c T / Σ_c ρ))`` (a normalised Gaussian average over
    the trusted pixels): the other frame passes on its reflectance levels, smooth, and this
    frame's ``ρ`` its detail and edges. Its weight is ``γ_T = weight · γ_a · value_scale``
    (the data term's weight, so the term keeps its ratio to the data term along the §3.4
    schedule).

    Returns:
        ``(γ_T, term)``, or ``None`` when the weight is 0 or no pixel is trusted.
    """
    gamma = prior.weight * weights.gamma_a * options.value_scale
    conf = prior.confidence.to(rho.dtype).clamp(0, 1)
    if mask is not None:
        conf = conf * mask
    if not gamma > 0 or not bool((conf > 0).any()):
        return None
    target = prior.target.to(rho.dtype).clamp_min(0)
    t_sum, r_sum = target.sum(1, keepdim=True), rho.sum(1, keepdim=True)
    ok = (conf > 0.5) & (t_sum > 1e-3) & (r_sum > 1e-3)
    kappa = torch.ones(rho.shape[0], dtype=rho.dtype, device=rho.device)
    for i in range(rho.shape[0]):
        if bool(ok[i].any()):
            kappa[i] = (r_sum[i][ok[i]] / t_sum[i][ok[i]]).median()
    target = target * kappa.view(-1, 1, 1, 1)
    if prior.sigma > 0 and bool(ok.any()):
        w = ok.to(rho.dtype)
        log_ratio = (t_sum * kappa.view(-1, 1, 1, 1)).clamp_min(1e-6) / r_sum.clamp_min(1e-6)
        log_ratio = log_ratio.log_() * w
        side = 2 * int(math.ceil(3 * prior.sigma)) + 1
        side = min(side, 2 * (min(rho.shape[-2:]) // 2) - 1)
        sig = (float(prior.sigma), float(prior.sigma))
        num = kornia.filters.gaussian_blur2d(log_ratio, (side, side), sig, border_type="reflect")
        den = kornia.filters.gaussian_blur2d(w, (side, side), sig, border_type="reflect")
        smooth = torch.where(den > 1e-3, num / den.clamp_min(1e-6), torch.zeros_like(num))
        target = torch.where(ok, rho * smooth.exp(), target)
    if prior.norm == "l1":
        return float(gamma), TemporalL1Term(target, conf)
    coefficient = 2.0 * gamma / (options.theta * options.value_scale)
    return float(gamma), TemporalAnchorTerm(target, conf, coefficient)
