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
as the stopping rule, and its residuals drive residual balancing of ``θ`` (``theta_range``).

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

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.solvers.pcg import pcg

__all__ = ["SplitBregmanResult", "split_bregman", "change_penalty", "GAP_FLOOR"]

logger = logging.getLogger(__name__)

#: the duality gap is relative to ``max(J(z), GAP_FLOOR · J(0))`` (``J(0) = γ_a ‖ρ‖²``)
GAP_FLOOR = 1e-3


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


def split_bregman(
    rho: torch.Tensor,
    terms: Sequence[Any],
    gammas: Sequence[float],
    *,
    gamma_a: float = 1.0,
    theta: float = 40.0,
    z0: torch.Tensor | None = None,
    tol: float = 1e-3,
    max_outer: int = 5,
    cg_tol: float = 1e-3,
    cg_max_iter: int = 10,
    track_objective: bool = True,
    gap_tol: float | None = None,
    check_every: int = 5,
    theta_range: tuple[float, float] | None = None,
    balance: tuple[float, float] = (10.0, 1.0),
) -> SplitBregmanResult:
    """Solve ``min_z γ_a‖z − ρ‖² + Σ_k γ_k ‖W_k M_k z‖₁`` by Split-Bregman (Eqs. 12–13).

    Args:
        rho: the data ``ρ``.
        terms: weighted difference operators ``W_k M_k`` (``StencilL1Term``, ``PairL1Term``).
        gammas: ``γ_k >= 0`` per term.
        gamma_a: data weight ``γ_a > 0``.
        theta: splitting penalty ``θ > 0``.
        z0: start (default ``ρ``).
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

    Returns:
        :class:`SplitBregmanResult`.

    Shape:
        rho, z0 ``(B, C, H, W)``; any float dtype and device (constants follow ``rho``).
    """
    check_shape(rho, ("B", "C", "H", "W"), "rho")
    if not rho.is_floating_point():
        raise ShapeError(f"expected floating rho, got {rho.dtype}")
    check_finite(rho, "rho")
    if len(terms) != len(gammas):
        raise ParameterError(f"got {len(terms)} terms but {len(gammas)} weights gamma")
    if any(not g >= 0 for g in gammas):
        raise ParameterError(f"term weights gamma must be >= 0, got {list(gammas)}")
    if not gamma_a > 0 or not theta > 0:
        raise ParameterError(f"gamma_a and theta must be > 0, got {gamma_a} and {theta}")
    if gap_tol is not None and not (gap_tol > 0 and check_every >= 1):
        raise ParameterError(f"need gap_tol > 0 and check_every >= 1, got {gap_tol}, {check_every}")
    if not balance[0] >= balance[1] > 0:
        raise ParameterError(f"balance must hold lower >= raise > 0, got {balance}")
    if theta_range is not None and not (0 < theta_range[0] <= theta <= theta_range[1]):
        raise ParameterError(
            f"theta_range must hold 0 < lo <= theta <= hi, got {theta_range}, theta {theta}"
        )
    if max_outer < 0 or cg_max_iter < 1:
        raise ParameterError(
            f"need max_outer >= 0, cg_max_iter >= 1; got {max_outer}, {cg_max_iter}"
        )
    rho = rho.contiguous()  # channels-last strides make the stencil products ~5x slower
    z = (rho if z0 is None else z0).clone(memory_format=torch.contiguous_format)
    if z.shape != rho.shape:
        raise ShapeError(f"z0 has shape {tuple(z.shape)} but rho has shape {tuple(rho.shape)}")
    check_finite(z, "z0")
    bsz, c, h, w = rho.shape
    active_terms = [(t, g) for t, g in zip(terms, gammas, strict=True) if g > 0]
    lams = [g / theta for _, g in active_terms]
    gap_mode = gap_tol is not None and all(
        getattr(t, "bregman_stats", False) for t, _ in active_terms
    )
    if gap_tol is not None and not gap_mode:
        logger.debug("split-bregman: a term measures no duality gap; stopping on the change")
    data_rhs = 2.0 * gamma_a * rho
    # the data's energy J(0) = γ_a‖ρ‖² per image: the gap's floor and the distance's scale
    energy0 = gamma_a * rho.square().flatten(1).sum(dim=1) if gap_mode else None
    floor = GAP_FLOOR * energy0 if gap_mode else None

    def bregman(z: torch.Tensor, states: list[torch.Tensor | None], final: bool, stats: bool):
        rhs = data_rhs.clone()
        obj = gamma_a * (z - rho).square().flatten(1).sum(dim=1) if track_objective else None
        measured = []
        for n, ((term, g), lam) in enumerate(zip(active_terms, lams, strict=True)):
            # final: no later step reads this state; a term that keeps no state for a later
            # solve need not store it (StencilL1Term: 60 planes per channel left unwritten)
            kw = {"final": True} if final and getattr(term, "skips_final_state", False) else {}
            if stats:
                kw["stats"] = True
            out = term.bregman_step(z, states[n], lam, with_l1=track_objective, **kw)
            states[n], r, l1 = out[:3]
            if stats:
                measured.append((g, out[3]))
            rhs = rhs.add_(r, alpha=theta)
            if track_objective:
                obj = obj + g * l1
        return rhs, obj, measured

    # None: the zero state; a term's initial_state (e.g. the previous alternation's) warm-starts
    states: list[torch.Tensor | None] = [getattr(t, "initial_state", None) for t, _ in active_terms]
    rhs, obj, _ = bregman(z, states, final=max_outer <= 1, stats=False)
    objective = [obj] if track_objective else None
    outer = torch.zeros(bsz, dtype=torch.long, device=rho.device)
    change = torch.zeros(bsz, dtype=rho.dtype, device=rho.device)
    cg_res = torch.zeros(bsz, dtype=rho.dtype, device=rho.device)
    gap = torch.full((bsz,), float("nan"), dtype=rho.dtype, device=rho.device)
    distance = torch.full_like(gap, float("nan"))
    active = torch.ones(bsz, dtype=torch.bool, device=rho.device)
    if not active_terms:
        # no L1 term: the minimiser is rho itself
        objective = obj.unsqueeze(0) if track_objective else None
        return SplitBregmanResult(
            rho.clone(), outer, 0, objective, change, torch.ones_like(active), cg_res,
            torch.zeros_like(gap), theta, torch.zeros_like(gap),
        )  # fmt: skip

    degree = sum(t.normal_diagonal() for t, _ in active_terms)

    def preconditioner() -> torch.Tensor:
        diag = 2.0 * gamma_a + theta * degree
        return (1.0 / diag).expand(bsz, c, h, w).reshape(bsz * c, 1, h, w)

    precond = preconditioner()

    def matvec(x: torch.Tensor) -> torch.Tensor:
        xi = x.view(bsz, c, h, w)
        out = None
        for t, _ in active_terms:
            y = t.normal_matvec(xi)  # a fresh tensor: accumulate in place
            out = y if out is None else out.add_(y)
        return out.mul_(theta).add_(xi, alpha=2.0 * gamma_a).view(bsz * c, 1, h, w)

    def sums(x: torch.Tensor) -> torch.Tensor:
        return x.flatten(1).sum(dim=1)

    cg_total = 0
    last = None  # the last z step's (rhs, PCGResult), for its residual
    next_check = check_every  # the iteration (1-based) of the next measurement of the gap
    previous = None  # the last measurement: (iteration, gaps)
    for it in range(max_outer):
        b_flat = rhs.reshape(bsz * c, 1, h, w)
        r0 = None
        if last is not None and last[1].r is not None and bool(active.all()):
            # z is the last step's solution: b' − A z = (b − A z) + (b' − b), no product
            r0 = last[1].r + (b_flat - last[0])
        res = pcg(
            matvec,
            b_flat,
            x0=z.reshape(bsz * c, 1, h, w),
            precond=precond,
            tol=cg_tol,
            max_iter=cg_max_iter,
            warn=False,
            true_residual=False,
            r0=r0,
        )
        last = (b_flat, res)
        cg_total += res.iterations
        cg_res = torch.where(active, res.residual.view(bsz, c).amax(dim=1), cg_res)
        z_new = res.x.view(bsz, c, h, w)
        step = (z_new - z).flatten(1).norm(dim=1) / z.flatten(1).norm(dim=1).clamp_min(1e-12)
        change = torch.where(active, step, change)
        z = torch.where(active.view(-1, 1, 1, 1), z_new, z)
        outer = outer + active.long()
        # when due (_next_check: at most every check_every iterations), and at the last update
        # before the cap (so a capped solve reports the gap of the z it returns, or of the one
        # before)
        check = gap_mode and (it + 1 == next_check or it == max_outer - 2)
        if it == max_outer - 1:
            # last iteration: only the objective is needed, skip the Bregman update
            obj_new = None
            if track_objective:
                obj_new = gamma_a * (z - rho).square().flatten(1).sum(dim=1)
                for t, g in active_terms:
                    obj_new = obj_new + g * t.l1(z)
        else:
            rhs, obj_new, measured = bregman(z, states, final=it == max_outer - 2, stats=check)
            if check:
                # the duality gap: p_k = b_k / λ_k is dual feasible (|p| <= 1), and with
                # g = Σ γ_k (W_k M_k)ᵀ p_k = θ Σ (W_k M_k)ᵀ b_k the dual objective is
                # D(p) = min_z γ_a‖z − ρ‖² + ⟨g, z⟩ = ⟨g, ρ⟩ − ‖g‖² / (4 γ_a) <= J(z*)
                g_adj = theta * sum(m.adjoint for _, m in measured)
                primal_obj = gamma_a * sums((z - rho).square()) + sum(g * m.l1 for g, m in measured)
                dual_obj = sums(g_adj * rho) - sums(g_adj.square()) / (4.0 * gamma_a)
                # relative to J(z), but at least to GAP_FLOOR · J(0) = GAP_FLOOR · γ_a‖ρ‖²: an
                # objective far below the data's own energy (a nearly flat image) leaves a gap
                # that float32 sums do not resolve relatively (a two-tone image: J ≈ 6e-6 J(0),
                # where the relative gap stalled at 9%)
                scale = torch.maximum(primal_obj, floor).clamp_min(torch.finfo(rho.dtype).tiny)
                now = (primal_obj - dual_obj) / scale
                gap = torch.where(active, now, gap)
                wait = _next_check(now, previous, it + 1, active, gap_tol, check_every)
                next_check = it + 1 + wait
                previous = (it + 1, now)
                # strong convexity: γ_a ‖z − z*‖² <= J(z) − J(z*) <= J(z) − D(p), relative to
                # ‖ρ‖: ‖z − z*‖² / ‖ρ‖² <= (J(z) − D(p)) / J(0)
                excess = (primal_obj - dual_obj).clamp_min(0.0)
                dist = (excess / energy0.clamp_min(torch.finfo(rho.dtype).tiny)).sqrt()
                distance = torch.where(active, dist, distance)
                if logger.isEnabledFor(logging.DEBUG):
                    logger.debug(
                        "split-bregman: iteration %d, duality gap %s", it + 1, now.tolist()
                    )
                if theta_range is not None:
                    new_theta = _balance(
                        z, rho, gamma_a, g_adj, measured, active & (now >= gap_tol),
                        theta, theta_range, balance,
                    )  # fmt: skip
                    if new_theta != theta:
                        # keep the multipliers θ b: b ← b θ_old / θ_new, and the z step's
                        # right-hand side θ Σ Mᵀ W (d − b) for the new θ and b
                        new_lams = [g / new_theta for _, g in active_terms]
                        rhs = change_penalty(
                            rhs, data_rhs, g_adj, states, active_terms, lams, new_lams,
                            new_theta / theta,
                        )  # fmt: skip
                        theta, lams = new_theta, new_lams
                        precond = preconditioner()
                        last = None
                        logger.debug("split-bregman: θ -> %g", theta)
        if track_objective:
            obj = torch.where(active, obj_new, obj)
            objective.append(obj)
        if gap_mode:
            if check:
                active = active & ~(gap < gap_tol)  # a NaN gap runs on to the cap
        else:
            active = active & (change >= tol)
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug("split-bregman: iteration %d, relative change %s", it + 1, change.tolist())
        if not bool(active.any()):
            break
    # without a measured gap (no update was measured), the change rule tells
    converged = torch.where(gap.isnan(), change < tol, gap < gap_tol) if gap_mode else change < tol
    return SplitBregmanResult(
        z=z,
        outer_iterations=outer,
        cg_iterations=cg_total,
        objective=torch.stack(objective) if track_objective else None,
        change=change,
        converged=converged,
        cg_residual=cg_res,
        gap=gap,
        theta=theta,
        distance=distance,
    )


def _next_check(now, previous, iteration, active, gap_tol, check_every) -> int:
    """Iterations until the next measurement of the duality gap (1 .. ``check_every``).

    The gaps ``now`` of the images still running are extrapolated at the rate measured since
    the ``previous`` measurement ``(iteration, gaps)``, ``r = (now / before)^(1 / Δ)`` per
    iteration; the next measurement comes when the first of them would reach ``gap_tol``.
    Without a previous measurement, or where no image's gap shrank, ``check_every``.
    """
    if previous is None:
        return check_every
    then, before = previous
    running = active & (now >= gap_tol) & (now > 0) & (before > now)
    if not bool(running.any()):
        return check_every
    # log of the per-iteration rate (< 0) and of the remaining factor (<= 0)
    log_rate = (now[running] / before[running]).log() / (iteration - then)
    need = float(((gap_tol / now[running]).log() / log_rate).ceil().min())
    if not math.isfinite(need):  # a rate that rounds to 1: no prediction
        return check_every
    return int(min(max(need, 1.0), float(check_every)))


def change_penalty(rhs, data_rhs, g_adj, states, active_terms, lams, new_lams, ratio):
    """Move a Split-Bregman iteration from penalty ``θ`` to ``θ' = ratio · θ``, in place.

    Keeps the Lagrange multipliers ``θ b``: each state becomes ``b · θ / θ'`` (the terms'
    ``rescale_state``; a 16-bit state only changes its step), and the next ``z`` step's
    right-hand side ``2γ_a ρ + θ Σ (W M)ᵀ (d − b)`` (``rhs``) becomes ``2γ_a ρ + θ' Σ (W M)ᵀ (d −
    b θ / θ')``, i.e. ``2γ_a ρ + ratio (rhs − 2γ_a ρ) + (ratio − 1) g`` with ``g = θ Σ (W M)ᵀ b``
    (``g_adj``, measured with the update): no pass over the state. Returns the new ``rhs``.
    """
    for n, (t, _) in enumerate(active_terms):
        states[n] = t.rescale_state(states[n], lams[n], new_lams[n])
    rhs = rhs.sub_(data_rhs).mul_(ratio).add_(data_rhs)
    return rhs.add_(g_adj, alpha=ratio - 1.0)


def _balance(z, rho, gamma_a, g_adj, measured, which, theta, theta_range, balance) -> float:
    """Residual balancing (Boyd et al. 2011, §3.4.1) on relative residuals, over ``which``.

    Primal: ``‖W M z − d‖ / max(‖W M z‖, ‖d‖)``; dual: the stationarity residual of the
    Lagrangian, ``‖2γ_a (z − ρ) + g‖ / ‖g‖`` (``g = θ Σ (W M)ᵀ b``). ``θ`` halves when the dual
    one is ``balance[0]`` times the primal one, doubles when the primal one is ``balance[1]``
    times the dual one, within ``theta_range``.
    """
    if not bool(which.any()):
        return theta
    sel = which.nonzero().flatten()
    primal = sum(m.primal for _, m in measured)[sel].sum().sqrt()
    scale = torch.maximum(
        sum(m.apply_sq for _, m in measured)[sel].sum(),
        sum(m.split_sq for _, m in measured)[sel].sum(),
    ).sqrt()
    dual = (2.0 * gamma_a * (z - rho) + g_adj)[sel].square().sum().sqrt()
    dual_scale = g_adj[sel].square().sum().sqrt()
    r = float(primal / scale.clamp_min(1e-30))
    s = float(dual / dual_scale.clamp_min(1e-30))
    logger.debug("split-bregman: relative residuals primal %.3g, dual %.3g at θ %g", r, s, theta)
    lower, raise_ = balance
    if s > lower * r:
        return max(0.5 * theta, theta_range[0])
    if r > raise_ * s:
        return min(2.0 * theta, theta_range[1])
    return theta
