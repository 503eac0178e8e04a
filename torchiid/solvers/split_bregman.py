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
gives the images' one-by-one results.

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.solvers.pcg import pcg

__all__ = ["SplitBregmanResult", "split_bregman"]

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
    """

    z: torch.Tensor
    outer_iterations: torch.Tensor
    cg_iterations: int
    objective: torch.Tensor | None
    change: torch.Tensor
    converged: torch.Tensor
    cg_residual: torch.Tensor


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

    def bregman(z: torch.Tensor, states: list[torch.Tensor | None], final: bool):
        rhs = 2.0 * gamma_a * rho
        obj = gamma_a * (z - rho).square().flatten(1).sum(dim=1) if track_objective else None
        for n, ((term, g), lam) in enumerate(zip(active_terms, lams, strict=True)):
            # final: no later step reads this state; a term that keeps no state for a later
            # solve need not store it (StencilL1Term: 60 planes per channel left unwritten)
            kw = {"final": True} if final and getattr(term, "skips_final_state", False) else {}
            states[n], r, l1 = term.bregman_step(z, states[n], lam, with_l1=track_objective, **kw)
            rhs = rhs.add_(r, alpha=theta)
            if track_objective:
                obj = obj + g * l1
        return rhs, obj

    # None: the zero state; a term's initial_state (e.g. the previous alternation's) warm-starts
    states: list[torch.Tensor | None] = [getattr(t, "initial_state", None) for t, _ in active_terms]
    rhs, obj = bregman(z, states, final=max_outer <= 1)
    objective = [obj] if track_objective else None
    outer = torch.zeros(bsz, dtype=torch.long, device=rho.device)
    change = torch.zeros(bsz, dtype=rho.dtype, device=rho.device)
    cg_res = torch.zeros(bsz, dtype=rho.dtype, device=rho.device)
    active = torch.ones(bsz, dtype=torch.bool, device=rho.device)
    if not active_terms:
        # no L1 term: the minimiser is rho itself
        objective = obj.unsqueeze(0) if track_objective else None
        return SplitBregmanResult(
            rho.clone(), outer, 0, objective, change, torch.ones_like(active), cg_res
        )

    diag = 2.0 * gamma_a + theta * sum(t.normal_diagonal() for t, _ in active_terms)
    precond = (1.0 / diag).expand(bsz, c, h, w).reshape(bsz * c, 1, h, w)

    def matvec(x: torch.Tensor) -> torch.Tensor:
        xi = x.view(bsz, c, h, w)
        out = None
        for t, _ in active_terms:
            y = t.normal_matvec(xi)  # a fresh tensor: accumulate in place
            out = y if out is None else out.add_(y)
        return out.mul_(theta).add_(xi, alpha=2.0 * gamma_a).view(bsz * c, 1, h, w)

    cg_total = 0
    last = None  # the last z step's (rhs, PCGResult), for its residual
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
        if it == max_outer - 1:
            # last iteration: only the objective is needed, skip the Bregman update
            obj_new = None
            if track_objective:
                obj_new = gamma_a * (z - rho).square().flatten(1).sum(dim=1)
                for t, g in active_terms:
                    obj_new = obj_new + g * t.l1(z)
        else:
            rhs, obj_new = bregman(z, states, final=it == max_outer - 2)
        if track_objective:
            obj = torch.where(active, obj_new, obj)
            objective.append(obj)
        active = active & (change >= tol)
        logger.debug("split-bregman: iteration %d, relative change %s", it + 1, change.tolist())
        if not bool(active.any()):
            break
    return SplitBregmanResult(
        z=z,
        outer_iterations=outer,
        cg_iterations=cg_total,
        objective=torch.stack(objective) if track_objective else None,
        change=change,
        converged=change < tol,
        cg_residual=cg_res,
    )
