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
import time
from dataclasses import dataclass

import torch

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_image, check_same_batch, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.reflectance_terms import (
    COLOUR_WEIGHTS,
    StencilL1Term,
    lab_features,
    merged_stencil_affinity,
    stencil_affinity,
)
from torchiid.priors.representatives import global_pair_term, representative_pixels
from torchiid.priors.stencil import Stencil
from torchiid.solvers.split_bregman import SplitBregmanResult, split_bregman
from torchiid.stages.config import ReflectanceOptions, ReflectanceProblem, ReflectanceWeights

__all__ = [
    "ReflectanceCache",
    "ReflectanceTimings",
    "ReflectanceResult",
    "ReflectanceTerms",
    "build_reflectance_terms",
    "solve_reflectance",
    "shading_from_ratio",
]

logger = logging.getLogger(__name__)


@dataclass
class ReflectanceCache:
    """Parts of Eq. 12 that do not change between the alternations on one image.

    The proposal-feature factor ``exp(−‖Δg̊‖²/2t_g²)`` of ``B``'s weights (Eq. 9) depends only
    on Stage 0's ``g̊`` and the mask, not on the current ``ρ``, so the pipeline computes it once
    per image batch and reuses it; it is recomputed when its inputs (same tensors, unmodified)
    or parameters differ. It also keeps the storage of the Bregman variable (``(B, 3, K, H, W)``,
    the stage's largest tensor) so that later alternations write into memory already in use.

    Attributes:
        semantic: (key of the inputs, ``(B, K, H, W)`` factor) or ``None``.
        hits: how many computations were skipped.
    """

    semantic: tuple[InputKey, torch.Tensor] | None = None
    hits: int = 0
    _state: torch.Tensor | None = None

    def state_buffer(self, like: torch.Tensor, num_offsets: int) -> torch.Tensor:
        """Storage ``(B, C, K, H, W)`` for the Bregman variable, reused across calls."""
        b, c, h, w = like.shape
        shape = (b, c, num_offsets, h, w)
        st = self._state
        if st is None or st.shape != shape or st.dtype != like.dtype or st.device != like.device:
            self._state = st = like.new_empty(shape)
        return st


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
            (the merged local and mid-level term) or ``"A"`` and ``"B"``, then ``"C"``.
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
        key = input_key(gpca, t_m, mask, rho.dtype, o.window)
        if cache is not None and cache.semantic is not None and cache.semantic[0] == key:
            e_g = cache.semantic[1]
            cache.hits += 1
        else:
            e_g = stencil_affinity(gpca.to(rho.dtype), stencil, t_m, mask)
            if cache is not None:
                cache.semantic = (key, e_g)
    t2 = time.perf_counter()
    if use_a and use_b and o.merge_stencil_terms:
        gl, gm = weights.gamma_l, weights.gamma_m
        merged = merged_stencil_affinity(rbar, e_g, stencil, o.t, gl, gm, mask)
        state = None if cache is None else cache.state_buffer(rho, stencil.num_offsets)
        terms["A+B"] = (
            float(gl + gm),
            StencilL1Term(stencil, merged, zero_invalid=False, state=state),
        )
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
        reps = representative_pixels(rbar, problem.segments, mask)
        terms["C"] = (float(weights.gamma_g), global_pair_term(rbar, reps, o.t))
        nrep = reps.counts
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
    built = build_reflectance_terms(problem, weights, options, cache)
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
        theta=o.theta * o.value_scale,
        z0=z0,
        tol=o.tol,
        max_outer=o.max_outer,
        cg_tol=o.cg_tol,
        cg_max_iter=o.cg_max_iter,
        track_objective=o.track_objective,
    )
    t5 = time.perf_counter()
    refl = sol.z.clamp_min(0.0)
    if mask is not None:
        refl = torch.where(mask, refl, rho)
    shading = shading_from_ratio(image, refl, o.eps)
    t_feat, t_local, t_mid, t_global = built.timings
    timings = ReflectanceTimings(t_feat, t_local, t_mid, t_global, t5 - t4)
    return ReflectanceResult(refl, shading, sol, built.num_representatives, timings)
