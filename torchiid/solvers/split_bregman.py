"""Split-Bregman (Goldstein & Osher 2009) for weighted anisotropic L1–L2 problems.

Minimises, per image and channel (paper Eqs. 12–13),

    J(z) = γ_a ‖z − ρ‖² + Σ_k γ_k ‖W_k M_k z‖₁

by splitting ``d_k = W_k M_k z`` and iterating (``λ_k = γ_k / θ``)

    z   ← argmin γ_a ‖z − ρ‖² + θ/2 Σ_k ‖d_k − W_k M_k z − b_k‖²
          i.e. (2γ_a I + θ Σ_k M_kᵀ W_k² M_k) z = 2γ_a ρ + θ Σ_k M_kᵀ W_k (d_k − b_k),
    d_k ← shrink(W_k M_k z + b_k, λ_k),    b_k ← b_k + W_k M_k z − d_k.

The ``z`` step is solved inexactly by Jacobi-preconditioned CG warm-started from the previous
``z`` (Goldstein & Osher use a single Gauss–Seidel sweep; Bregman iterations absorb the error).
The iteration starts at ``z0`` (default ``ρ``) with ``b_k = 0`` followed by one Bregman update, so
a good ``z0`` is kept rather than first smoothed away. Each image stops when
``‖z_new − z‖ / ‖z‖ < tol`` (its ``z`` is then frozen) or after ``max_outer`` iterations; a batch
gives the images' one-by-one results (except with ``theta_range``: the images of a batch share
``θ``, balanced on their pooled residuals, so each still stops at its own gap but along another
path).

Duality gap (``gap_tol``). The clamped Bregman variable gives a dual-feasible point ``p_k = b_k /
λ_k`` (``|p_k| <= 1``), and Eq. 12's dual ``D(p) = ⟨g, ρ⟩ − ‖g‖² / (4γ_a)``, ``g = Σ_k γ_k (W_k
M_k)ᵀ p_k``, bounds the minimum from below: ``(J(z) − D(p)) / J(z)`` bounds how far ``J(z)`` is
above it, relatively, whatever ``θ`` and the start. Measured every few iterations from the
Bregman update's own pass (``bregman_step(..., stats=True)``), it replaces the change of ``z``
as the stopping rule, and its residuals drive residual balancing of ``θ`` (``theta_range``;
:mod:`torchiid.solvers.bregman_gap`).

Terms are duck-typed (see :mod:`torchiid.priors.reflectance_terms`):
``bregman_step(z, b, λ, with_l1) -> (b, rhs, l1)`` (``b=None``: the zero state),
``normal_matvec(z)``, ``normal_diagonal()``, ``l1(z)``; optionally ``initial_state`` (a
Bregman variable to start from instead of the zero state, updated in place) and
``skips_final_state``: when true, the last Bregman update of a solve is called with
``final=True`` and the term may leave its state unwritten (no later step reads it).

Each ``z`` step after the first starts its CG from the last one's residual, corrected by the
change of the right-hand side (``b' − A z = (b − A z) + (b' − b)``), instead of a product.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.solvers.bregman_gap import GAP_FLOOR, Gap, measure_gap
from torchiid.solvers.pcg import PCGResult, pcg
from torchiid.solvers.splitting import Splitting, change_penalty

__all__ = [
    "SplitBregmanOptions",
    "SplitBregmanResult",
    "split_bregman",
    "change_penalty",
    "GAP_FLOOR",
]


@dataclass(frozen=True)
class SplitBregmanOptions:
    """The settings of a :func:`split_bregman` solve (not of the energy it minimises).

    Attributes:
        theta: splitting penalty ``θ > 0``.
        tol: per-image stopping threshold on the relative change of ``z``.
        max_outer: maximum Bregman iterations.
        cg_tol: relative residual tolerance of each ``z`` step.
        cg_max_iter: CG iteration cap of each ``z`` step (partial solves are expected, so no
            warning is emitted; the residual is reported).
        track_objective: evaluate ``J`` after every iteration (the L1 norms cost about a third
            of a Bregman update; the pipeline turns this off).
        gap_tol: stop each image when its relative duality gap falls below this, measured
            at most every ``check_every`` iterations, instead of on the change of ``z`` (``tol``
            is then unused). The gap is ``J(z) − D(p)`` over ``max(J(z), GAP_FLOOR · J(0))``:
            below a thousandth of the data's energy ``J(0) = γ_a ‖ρ‖²`` it is absolute.
            Needs terms with ``bregman_stats`` (the difference terms); with others the
            change rule applies.
        check_every: the most iterations between two measurements of the gap. From the
            second measurement on, the next one comes when the gap, shrinking at the rate
            measured between the last two, would reach ``gap_tol`` (at least 1 iteration
            later, at most ``check_every``), so a solve usually runs fewer iterations past
            its tolerance than a fixed interval would (in a batch, the image predicted to get
            there first sets the schedule).
        theta_range: ``(θ_lo, θ_hi)``: with ``gap_tol``, residual balancing (Boyd et al. 2011,
            §3.4.1) at every measurement: halve ``θ`` (down to ``θ_lo``) when the relative dual
            residual exceeds ``balance[0]`` times the relative primal one, double it (up to
            ``θ_hi``) when the primal one exceeds ``balance[1]`` times the dual one. The
            Lagrange multipliers ``θ b`` are kept across a change.
        balance: ``(lower, raise)``, the residual ratios that change ``θ``. The default
            lowers ``θ`` only on strong evidence and raises it back as soon as the primal
            residual dominates: a small penalty gains most early and can slow the tail.
    """

    theta: float = 40.0
    tol: float = 1e-3
    max_outer: int = 5
    cg_tol: float = 1e-3
    cg_max_iter: int = 10
    track_objective: bool = True
    gap_tol: float | None = None
    check_every: int = 5
    theta_range: tuple[float, float] | None = None
    balance: tuple[float, float] = (10.0, 1.0)


logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SplitBregmanResult:
    """Result of :func:`split_bregman`.

    Attributes:
        z: the solution ``(B, C, H, W)``.
        outer_iterations: ``(B,)`` Bregman iterations run per image.
        cg_iterations: CG iterations summed over all ``z`` steps (batch maximum per step).
        objective: ``(T + 1, B)`` objective ``J`` at ``z0`` and after each outer iteration
            (frozen images repeat their last value); ``None`` when not tracked.
        change: ``(B,)`` last relative change of ``z``.
        converged: ``(B,)`` bool, whether the relative change fell below ``tol``.
        cg_residual: ``(B,)`` largest relative CG residual of the last ``z`` step over channels.
        gap: ``(B,)`` the last measured relative duality gap ``(J(z) − D(p)) / max(J(z),
            GAP_FLOOR · J(0))`` (an upper bound on ``z``'s relative excess over the minimum
            where ``J(z) >= GAP_FLOOR · J(0)``, else on its excess over ``GAP_FLOOR · J(0)``;
            ``nan`` where none was measured). Measured at the last update before the cap, so
            a capped solve's gap is that of the iterate before the returned one.
        theta: the penalty ``θ`` of the last iteration (it changes with ``theta_range``).
        distance: ``(B,)`` a certified bound on the distance of ``z`` to the exact minimiser
            ``z*``, relative to ``ρ``: ``‖z − z*‖ / ‖ρ‖ <= sqrt((J(z) − D(p)) / (γ_a ‖ρ‖²))``
            (``J`` is ``2γ_a``-strongly convex, so ``J(z) − J(z*) >= γ_a ‖z − z*‖²``, and
            ``D(p) <= J(z*)``); from the same measurement as ``gap``, ``nan`` where none.
    """

    z: torch.Tensor
    outer_iterations: torch.Tensor
    cg_iterations: int
    objective: torch.Tensor | None
    change: torch.Tensor
    converged: torch.Tensor
    cg_residual: torch.Tensor
    gap: torch.Tensor | None = None
    theta: float | None = None
    distance: torch.Tensor | None = None


def _check(
    rho: torch.Tensor, gammas: Sequence[float], count: int, gamma_a: float, o: SplitBregmanOptions
) -> None:
    check_shape(rho, ("B", "C", "H", "W"), "rho")
    if not rho.is_floating_point():
        raise ShapeError(f"expected floating rho, got {rho.dtype}")
    check_finite(rho, "rho")
    if count != len(gammas):
        raise ParameterError(f"got {count} terms but {len(gammas)} weights gamma")
    if any(not g >= 0 for g in gammas):
        raise ParameterError(f"term weights gamma must be >= 0, got {list(gammas)}")
    if not gamma_a > 0 or not o.theta > 0:
        raise ParameterError(f"gamma_a and theta must be > 0, got {gamma_a} and {o.theta}")
    if o.gap_tol is not None and not (o.gap_tol > 0 and o.check_every >= 1):
        raise ParameterError(
            f"need gap_tol > 0 and check_every >= 1, got {o.gap_tol}, {o.check_every}"
        )
    if not o.balance[0] >= o.balance[1] > 0:
        raise ParameterError(f"balance must hold lower >= raise > 0, got {o.balance}")
    rng = o.theta_range
    if rng is not None and not (0 < rng[0] <= o.theta <= rng[1]):
        raise ParameterError(
            f"theta_range must hold 0 < lo <= theta <= hi, got {rng}, theta {o.theta}"
        )
    if o.max_outer < 0 or o.cg_max_iter < 1:
        raise ParameterError(
            f"need max_outer >= 0, cg_max_iter >= 1; got {o.max_outer}, {o.cg_max_iter}"
        )


def split_bregman(
    rho: torch.Tensor,
    terms: Sequence[Any],
    gammas: Sequence[float],
    *,
    gamma_a: float = 1.0,
    z0: torch.Tensor | None = None,
    options: SplitBregmanOptions | None = None,
) -> SplitBregmanResult:
    """Solve ``min_z γ_a‖z − ρ‖² + Σ_k γ_k ‖W_k M_k z‖₁`` by Split-Bregman (Eqs. 12–13).

    Args:
        rho: the data ``ρ``.
        terms: weighted difference operators ``W_k M_k`` (``StencilL1Term``, ``PairL1Term``).
        gammas: ``γ_k >= 0`` per term.
        gamma_a: data weight ``γ_a > 0``.
        z0: start (default ``ρ``).
        options: the solver's settings (:class:`SplitBregmanOptions`; default its defaults).

    Returns:
        :class:`SplitBregmanResult`.

    Shape:
        rho, z0 ``(B, C, H, W)``; any float dtype and device (constants follow ``rho``).
    """
    o = options or SplitBregmanOptions()
    _check(rho, gammas, len(terms), gamma_a, o)
    rho = rho.contiguous()  # channels-last strides make the stencil products ~5x slower
    z = (rho if z0 is None else z0).clone(memory_format=torch.contiguous_format)
    if z.shape != rho.shape:
        raise ShapeError(f"z0 has shape {tuple(z.shape)} but rho has shape {tuple(rho.shape)}")
    check_finite(z, "z0")
    active_terms = [(t, g) for t, g in zip(terms, gammas, strict=True) if g > 0]
    gap_mode = o.gap_tol is not None and all(
        getattr(t, "bregman_stats", False) for t, _ in active_terms
    )
    if o.gap_tol is not None and not gap_mode:
        logger.debug("split-bregman: a term measures no duality gap; stopping on the change")
    sp = Splitting(rho, active_terms, gamma_a, o.theta, o.track_objective)
    rhs, obj, _ = sp.bregman(z, final=o.max_outer <= 1, stats=False)
    if not active_terms:
        # no L1 term: the minimiser is rho itself
        return _unsplit(rho, obj, o.theta)
    gap = None
    if gap_mode and o.gap_tol is not None:
        gap = Gap.unmeasured(rho, gamma_a, o.gap_tol, o.check_every)
    return _iterate(sp, z, (rhs, obj), o, gap)


def _unsplit(rho: torch.Tensor, obj: torch.Tensor | None, theta: float) -> SplitBregmanResult:
    """The result without an active L1 term: ``z = ρ``, converged at once."""
    bsz = rho.shape[0]
    zeros = torch.zeros(bsz, dtype=rho.dtype, device=rho.device)
    outer = torch.zeros(bsz, dtype=torch.long, device=rho.device)
    done = torch.ones(bsz, dtype=torch.bool, device=rho.device)
    objective = None if obj is None else obj.unsqueeze(0)
    return SplitBregmanResult(
        rho.clone(), outer, 0, objective, zeros, done, zeros.clone(), zeros.clone(), theta,
        zeros.clone(),
    )  # fmt: skip


def _iterate(
    sp: Splitting,
    z: torch.Tensor,
    start: tuple[torch.Tensor, torch.Tensor | None],
    o: SplitBregmanOptions,
    gap: Gap | None,
) -> SplitBregmanResult:
    """The outer iterations from ``z`` after the first Bregman update (``start``: its rhs, J).

    ``gap``: stop on the duality gap (``None``: on the change of ``z``).
    """
    rhs, obj = start
    bsz, c, h, w = z.shape
    rho = sp.rho
    objective = [obj] if obj is not None else None
    outer = torch.zeros(bsz, dtype=torch.long, device=rho.device)
    change = rho.new_zeros(bsz)
    cg_res = rho.new_zeros(bsz)
    active = torch.ones(bsz, dtype=torch.bool, device=rho.device)
    precond = sp.preconditioner()
    solve = functools.partial(
        pcg, tol=o.cg_tol, max_iter=o.cg_max_iter, warn=False, true_residual=False
    )
    cg_total = 0
    last: tuple[torch.Tensor, PCGResult] | None = None  # the last z step's rhs and result
    for it in range(o.max_outer):
        b_flat = rhs.reshape(bsz * c, 1, h, w)
        r0 = None
        if last is not None and last[1].r is not None and bool(active.all()):
            # z is the last step's solution: b' − A z = (b − A z) + (b' − b), no product
            r0 = last[1].r + (b_flat - last[0])
        res = solve(sp.matvec, b_flat, x0=z.reshape(bsz * c, 1, h, w), precond=precond, r0=r0)
        last = (b_flat, res)
        cg_total += res.iterations
        cg_res = torch.where(active, res.residual.view(bsz, c).amax(dim=1), cg_res)
        z_new = res.x.view(bsz, c, h, w)
        step = (z_new - z).flatten(1).norm(dim=1) / z.flatten(1).norm(dim=1).clamp_min(1e-12)
        change = torch.where(active, step, change)
        z = torch.where(active.view(-1, 1, 1, 1), z_new, z)
        outer = outer + active.long()
        # when due (at most every check_every iterations), and at the last update before the
        # cap (so a capped solve reports the gap of the z it returns, or of the one before)
        check = gap is not None and (it + 1 == gap.next_check or it == o.max_outer - 2)
        if it == o.max_outer - 1:
            # last iteration: only the objective is needed, skip the Bregman update
            obj_new = sp.objective(z)
        else:
            rhs, obj_new, measured = sp.bregman(z, it == o.max_outer - 2, check)
            if check and gap is not None:
                balancing = None if o.theta_range is None else (o.theta_range, o.balance)
                rhs, retuned = measure_gap(sp, gap, z, rhs, measured, active, it + 1, balancing)
                if retuned:
                    precond = sp.preconditioner()
                    last = None
        if objective is not None and obj is not None and obj_new is not None:
            obj = torch.where(active, obj_new, obj)
            objective.append(obj)
        if gap is not None:
            if check:
                active = active & ~(gap.value < gap.tol)  # a NaN gap runs on to the cap
        else:
            active = active & (change >= o.tol)
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug("split-bregman: iteration %d, relative change %s", it + 1, change.tolist())
        if not bool(active.any()):
            break
    if gap is not None:
        # without a measured gap (no update was measured), the change rule tells
        converged = torch.where(gap.value.isnan(), change < o.tol, gap.value < gap.tol)
    else:
        converged = change < o.tol
    return SplitBregmanResult(
        z=z,
        outer_iterations=outer,
        cg_iterations=cg_total,
        objective=torch.stack(objective) if objective is not None else None,
        change=change,
        converged=converged,
        cg_residual=cg_res,
        gap=gap.value if gap is not None else rho.new_full((bsz,), float("nan")),
        theta=sp.theta,
        distance=gap.distance if gap is not None else rho.new_full((bsz,), float("nan")),
    )
