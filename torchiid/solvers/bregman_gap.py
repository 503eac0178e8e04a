"""Split-Bregman's duality gap: the stopping rule, its schedule and residual balancing of ``θ``.

The clamped Bregman variable gives a dual-feasible point ``p_k = b_k / λ_k`` (``|p_k| <= 1``);
with ``g = Σ_k γ_k (W_k M_k)ᵀ p_k = θ Σ_k (W_k M_k)ᵀ b_k`` the dual objective is ``D(p) = min_z
γ_a‖z − ρ‖² + ⟨g, z⟩ = ⟨g, ρ⟩ − ‖g‖² / (4 γ_a) <= J(z*)``, so ``J(z) − D(p)`` bounds how far
``J(z)`` is above the minimum (:func:`measure_gap`). The same measurement gives the primal
and dual residuals that balance the penalty (:func:`balance`, Boyd et al. 2011, §3.4.1).
"""

from __future__ import annotations

import logging
import math
import operator
from collections.abc import Iterable
from dataclasses import dataclass
from functools import reduce

import torch

from torchiid.solvers.splitting import Measured, Splitting

__all__ = ["GAP_FLOOR", "Gap", "measure_gap", "next_check", "balance"]

logger = logging.getLogger("torchiid.solvers.split_bregman")

#: the duality gap is relative to ``max(J(z), GAP_FLOOR · J(0))`` (``J(0) = γ_a ‖ρ‖²``)
GAP_FLOOR = 1e-3


def _sums(x: torch.Tensor) -> torch.Tensor:
    return x.flatten(1).sum(dim=1)


def _total(values: Iterable[torch.Tensor]) -> torch.Tensor:
    """The sum of one or more tensors."""
    out: torch.Tensor = reduce(operator.add, values)
    return out


@dataclass
class Gap:
    """The duality gap of a solve, per image, and when to measure it next.

    Attributes:
        tol: the gap at which an image stops.
        check_every: the most iterations between two measurements.
        value: ``(B,)`` the last measured relative gap (``nan``: none yet).
        distance: ``(B,)`` the certified bound on ``‖z − z*‖ / ‖ρ‖`` of that measurement.
        energy0: ``(B,)`` the data's energy ``J(0) = γ_a ‖ρ‖²``.
        next_check: the iteration (1-based) of the next measurement.
        previous: the last measurement ``(iteration, gaps)``.
    """

    tol: float
    check_every: int
    value: torch.Tensor
    distance: torch.Tensor
    energy0: torch.Tensor
    next_check: int
    previous: tuple[int, torch.Tensor] | None = None

    @classmethod
    def unmeasured(cls, rho: torch.Tensor, gamma_a: float, tol: float, check_every: int) -> Gap:
        """No measurement yet; the first one after ``check_every`` iterations."""
        value = torch.full((rho.shape[0],), float("nan"), dtype=rho.dtype, device=rho.device)
        energy0 = gamma_a * _sums(rho.square())
        nan = torch.full_like(value, float("nan"))
        return cls(tol, check_every, value, nan, energy0, check_every)


def measure_gap(
    sp: Splitting,
    gap: Gap,
    z: torch.Tensor,
    rhs: torch.Tensor,
    measured: Measured,
    active: torch.Tensor,
    iteration: int,
    balancing: tuple[tuple[float, float], tuple[float, float]] | None,
) -> tuple[torch.Tensor, bool]:
    """Measure the gap at ``z`` from the update's stats (``gap`` updated), balance ``θ``.

    ``iteration``: 1-based. ``balancing``: ``(theta_range, ratios)`` of :func:`balance`, or
    ``None`` for a fixed ``θ``. Returns the next ``z`` step's right-hand side (changed when
    ``θ`` changes) and whether ``θ`` changed.
    """
    rho, gamma_a, tiny = sp.rho, sp.gamma_a, torch.finfo(sp.rho.dtype).tiny
    g_adj = sp.theta * _total(m.adjoint for _, m in measured)
    primal_obj = gamma_a * _sums((z - rho).square()) + _total(g * m.l1 for g, m in measured)
    dual_obj = _sums(g_adj * rho) - _sums(g_adj.square()) / (4.0 * gamma_a)
    # relative to J(z), but at least to GAP_FLOOR · J(0) = GAP_FLOOR · γ_a‖ρ‖²: an objective
    # far below the data's own energy (a nearly flat image) leaves a gap that float32 sums do
    # not resolve relatively
    scale = torch.maximum(primal_obj, GAP_FLOOR * gap.energy0).clamp_min(tiny)
    now = (primal_obj - dual_obj) / scale
    gap.value = torch.where(active, now, gap.value)
    gap.next_check = iteration + next_check(
        now, gap.previous, iteration, active, gap.tol, gap.check_every
    )
    gap.previous = (iteration, now)
    # strong convexity: γ_a ‖z − z*‖² <= J(z) − J(z*) <= J(z) − D(p), relative to ‖ρ‖:
    # ‖z − z*‖² / ‖ρ‖² <= (J(z) − D(p)) / J(0)
    excess = (primal_obj - dual_obj).clamp_min(0.0)
    dist = (excess / gap.energy0.clamp_min(tiny)).sqrt()
    gap.distance = torch.where(active, dist, gap.distance)
    if logger.isEnabledFor(logging.DEBUG):
        logger.debug("split-bregman: iteration %d, duality gap %s", iteration, now.tolist())
    if balancing is None:
        return rhs, False
    residuals = _residuals(sp, z, g_adj, measured, active & (now >= gap.tol))
    theta = balance(residuals, sp.theta, *balancing)
    if theta == sp.theta:
        return rhs, False
    # keep the multipliers θ b: b ← b θ_old / θ_new, and the z step's right-hand side
    # θ Σ Mᵀ W (d − b) for the new θ and b
    rhs = sp.retune(theta, g_adj, rhs)
    logger.debug("split-bregman: θ -> %g", theta)
    return rhs, True


def next_check(
    now: torch.Tensor,
    previous: tuple[int, torch.Tensor] | None,
    iteration: int,
    active: torch.Tensor,
    gap_tol: float,
    check_every: int,
) -> int:
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


def _residuals(
    sp: Splitting, z: torch.Tensor, g_adj: torch.Tensor, measured: Measured, which: torch.Tensor
) -> tuple[float, float] | None:
    """Relative primal and dual residuals over the images ``which`` (``None``: none).

    Primal: ``‖W M z − d‖ / max(‖W M z‖, ‖d‖)``; dual: the stationarity residual of the
    Lagrangian, ``‖2γ_a (z − ρ) + g‖ / ‖g‖`` (``g = θ Σ (W M)ᵀ b``).
    """
    if not bool(which.any()):
        return None
    sel = which.nonzero().flatten()
    primal = _total(m.primal for _, m in measured)[sel].sum().sqrt()
    scale = torch.maximum(
        _total(m.apply_sq for _, m in measured)[sel].sum(),
        _total(m.split_sq for _, m in measured)[sel].sum(),
    ).sqrt()
    dual = (2.0 * sp.gamma_a * (z - sp.rho) + g_adj)[sel].square().sum().sqrt()
    dual_scale = g_adj[sel].square().sum().sqrt()
    return float(primal / scale.clamp_min(1e-30)), float(dual / dual_scale.clamp_min(1e-30))


def balance(
    residuals: tuple[float, float] | None,
    theta: float,
    theta_range: tuple[float, float],
    ratios: tuple[float, float],
) -> float:
    """Residual balancing (Boyd et al. 2011, §3.4.1) of the penalty ``θ``.

    ``residuals``: the relative primal and dual residuals ``(r, s)``. ``θ`` halves when ``s >
    ratios[0] · r``, doubles when ``r > ratios[1] · s``, within ``theta_range``.
    """
    if residuals is None:
        return theta
    r, s = residuals
    logger.debug("split-bregman: relative residuals primal %.3g, dual %.3g at θ %g", r, s, theta)
    lower, raise_ = ratios
    if s > lower * r:
        return max(0.5 * theta, theta_range[0])
    if r > raise_ * s:
        return min(2.0 * theta, theta_range[1])
    return theta
