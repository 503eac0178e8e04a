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
non-negative weights, anisotropic L1). With ``merge=True`` (default) the solver
works on this single term, which halves time and memory; the minimiser is unchanged (the
Bregman splitting, hence the iterates after few iterations, differ slightly).

Video. A :class:`~torchiid.stages.config.TemporalPrior` in the problem adds a term ``"T"``
pulling ``z`` toward another frame's reflectance warped onto this one
(:mod:`torchiid.stages.temporal`). Without it (still images) nothing changes.

Scales. The paper's values (γ_l = γ_m = 20, γ_g = 2, θ = 40, §4) come from Bi et al.'s Matlab
code, which works on 8-bit values ``0..255``; ``γ_a`` is not given (1 here). So Eq. 12 is
evaluated on ``s·z`` (``s = value_scale = 255``) and divided by ``s``: on our ``[0, 1]`` linear
values the solver minimises ``Σ_k γ_k ‖W_k M_k z‖₁ + s·γ_a ‖z − ρ‖²`` with penalty ``s·θ``. With
``s = 1`` the L1 terms would outweigh the data term (γ_l · 120 neighbours against a weight of 1)
and the minimiser would merge colours across edges (the documentation's Method page, "Scale of
the L1 terms").

Colour weights. ``B``'s weights are ``v^l`` times a gate on ``A``'s pairs, so ``B`` only adds
flattening where ``A`` flattens; on ``g̊`` the gate (``t_g = t = 0.05``) is in effect a
same-atom indicator (pairs inside one atom have ``Δg̊ = 0``, pairs across atoms
``‖Δg̊‖ ≈ 0.3``). The default ``colour_weights="bi"`` are Bi et al.'s weights, 5–6× narrower
than the unscaled reading ``"wide"``: with them ``A`` keeps thin coloured prints and ``B``
helps (Method page, "Colour weights").
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from torchiid.params import ReflectanceParameters
from torchiid.solvers.split_bregman import (
    SplitBregmanOptions,
    SplitBregmanResult,
    split_bregman,
)
from torchiid.stages.config import ReflectanceProblem, check_group
from torchiid.stages.reflectance_system import (
    ReflectanceCache,
    ReflectanceTerms,
    assemble_reflectance_terms,
    build_reflectance_terms,
)
from torchiid.stages.temporal import TemporalAnchorTerm, TemporalL1Term, temporal_term

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


def solve_reflectance(
    problem: ReflectanceProblem,
    reflectance: ReflectanceParameters,
    *,
    z0: torch.Tensor | None = None,
    cache: ReflectanceCache | None = None,
    merge: bool = True,
    track_objective: bool = True,
) -> ReflectanceResult:
    """Reflectance formulation (Eq. 12) solved by Split-Bregman.

    Args:
        problem: ``ρ`` (the Stage 1 reflectance), the image, ``g̊`` for ``B``, the segments
            for ``C`` and the mask (:class:`~torchiid.stages.config.ReflectanceProblem`);
            pairs touching pixels outside the mask are dropped and ``R = ρ`` there.
        reflectance: the stage's parameters (:class:`~torchiid.params.ReflectanceParameters`,
            e.g. ``params.alternation(k)[1]``): the weights (``γ_l``, ``γ_m``, ``γ_g``: 0 or a
            switch is off; ``γ_a`` of the data term), the priors' constants and the
            Split-Bregman settings.
        z0: warm start (default ``ρ``), e.g. the previous alternation's ``R``.
        cache: reuse ``B``'s proposal-feature factor across calls on the same ``g̊``
            (:class:`ReflectanceCache`) and its Bregman-state storage.
        merge: solve ``A`` and ``B`` as one exactly equivalent term (see the module notes).
        track_objective: record Eq. 12's value after every Bregman iteration
            (:func:`~torchiid.decompose` does not).

    Returns:
        :class:`ReflectanceResult`.

    Shape:
        rho, image, z0 ``(B, 3, H, W)``; gpca ``(B, d, H, W)``; segments ``(B, H, W)`` long;
        mask ``(B, 1, H, W)`` bool.
    """
    o = check_group("solve_reflectance", reflectance, ReflectanceParameters, "reflectance")
    weights = o.weights()
    theta = o.theta * o.value_scale
    balanced = o.bregman_gap_tol > 0 and o.bregman_theta_floor < 1
    warm_theta = None
    if balanced and o.bregman_warm_state and cache is not None and cache.state_valid:
        warm_theta = cache.theta  # read before the terms are built (that clears state_valid)
    built = assemble_reflectance_terms(problem, o, weights, cache, merge)
    if warm_theta is not None and "T" not in built.terms:
        # the warm state's multipliers θ b were reached at this penalty: go on from it (not
        # with a temporal term, whose anchor coefficient 2γ/θ is made for the configured θ and
        # which keeps θ fixed: it measures no gap)
        theta = min(max(warm_theta, theta * o.bregman_theta_floor), theta)
    # Channels-last inputs (e.g. a permuted HxWx3 array) make every per-offset slice op
    # stride over interleaved channels, about 5x slower: work on contiguous planes.
    rho, image, mask = problem.rho.contiguous(), problem.image.contiguous(), problem.mask
    z0 = None if z0 is None else z0.contiguous()
    full = o.theta * o.value_scale
    t4 = time.perf_counter()
    settings = SplitBregmanOptions(
        theta=theta,
        tol=o.bregman_tol,
        max_outer=o.bregman_iter,
        cg_tol=o.bregman_cg_tol,
        cg_max_iter=o.bregman_cg_iter,
        track_objective=track_objective,
        gap_tol=o.bregman_gap_tol or None,
        theta_range=(full * o.bregman_theta_floor, full) if balanced else None,
    )
    sol = split_bregman(
        rho,
        [term for _, term in built.terms.values()],
        [gamma for gamma, _ in built.terms.values()],
        gamma_a=o.gamma_a * o.value_scale,
        z0=z0,
        options=settings,
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
    shading = shading_from_ratio(image, refl, o.shading_floor)
    t_feat, t_local, t_mid, t_global = built.timings
    timings = ReflectanceTimings(t_feat, t_local, t_mid, t_global, t5 - t4)
    return ReflectanceResult(refl, shading, sol, built.num_representatives, timings)
