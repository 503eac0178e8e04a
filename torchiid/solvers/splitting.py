"""Split-Bregman's penalised subproblems at a penalty ``θ``: the updates and the ``z`` step.

:class:`Splitting` holds the energy ``J(z) = γ_a ‖z − ρ‖² + Σ_k γ_k ‖W_k M_k z‖₁``, the penalty
``θ`` with the thresholds ``λ_k = γ_k / θ``, and the terms' Bregman variables; it runs the
Bregman updates over the terms and gives the ``z`` step's operator ``2γ_a I + θ Σ_k M_kᵀ W_k²
M_k`` with its Jacobi preconditioner. :func:`change_penalty` moves it to another ``θ``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["Splitting", "change_penalty", "Measured"]

#: a term's weight ``γ_k`` and what its update measured (``BregmanStats``)
Measured = list[tuple[float, Any]]


def _sums(x: torch.Tensor) -> torch.Tensor:
    return x.flatten(1).sum(dim=1)


class Splitting:
    """The subproblems of a Split-Bregman solve at penalty ``θ`` (see the module notes).

    Args:
        rho: the data ``ρ`` ``(B, C, H, W)``.
        terms: ``(term, γ_k)`` of the active L1 terms (``γ_k > 0``).
        gamma_a: data weight ``γ_a``.
        theta: the penalty ``θ``.
        track: evaluate the objective with every update.
    """

    def __init__(
        self,
        rho: torch.Tensor,
        terms: Sequence[tuple[Any, float]],
        gamma_a: float,
        theta: float,
        track: bool,
    ) -> None:
        self.rho = rho
        self.terms = list(terms)
        self.gamma_a = gamma_a
        self.theta = theta
        self.lams = [g / theta for _, g in self.terms]
        self.track = track
        self.data_rhs = 2.0 * gamma_a * rho
        # None: the zero state; a term's initial_state (e.g. the previous alternation's)
        # warm-starts
        self.states: list[Any] = [getattr(t, "initial_state", None) for t, _ in self.terms]
        self._degree: torch.Tensor | None = None  # Σ_k diag(M_kᵀ W_k² M_k), once needed

    def bregman(
        self, z: torch.Tensor, final: bool, stats: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None, Measured]:
        """Every term's Bregman update at ``z``: the next ``z`` step's rhs, ``J(z)``, the stats.

        ``final``: no later step reads the states; ``stats``: measure the updates.
        """
        rhs = self.data_rhs.clone()
        obj = self.gamma_a * _sums((z - self.rho).square()) if self.track else None
        measured: Measured = []
        for n, ((term, g), lam) in enumerate(zip(self.terms, self.lams, strict=True)):
            # final: no later step reads this state; a term that keeps no state for a later
            # solve need not store it (StencilL1Term: 60 planes per channel left unwritten)
            kw = {"final": True} if final and getattr(term, "skips_final_state", False) else {}
            if stats:
                kw["stats"] = True
            out = term.bregman_step(z, self.states[n], lam, with_l1=self.track, **kw)
            self.states[n], r, l1 = out[:3]
            if stats:
                measured.append((g, out[3]))
            rhs = rhs.add_(r, alpha=self.theta)
            if obj is not None:
                obj = obj + g * l1
        return rhs, obj, measured

    def objective(self, z: torch.Tensor) -> torch.Tensor | None:
        """``J(z)`` per image ``(B,)`` (``None`` when not tracked)."""
        if not self.track:
            return None
        obj = self.gamma_a * _sums((z - self.rho).square())
        for t, g in self.terms:
            obj = obj + g * t.l1(z)
        return obj

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """The ``z`` step's operator on ``(B C, 1, H, W)`` (one system per channel)."""
        bsz, c, h, w = self.rho.shape
        xi = x.view(bsz, c, h, w)
        out: torch.Tensor | None = None
        for t, _ in self.terms:
            y: torch.Tensor = t.normal_matvec(xi)  # a fresh tensor: accumulate in place
            out = y if out is None else out.add_(y)
        if out is None:
            raise ValueError("the z step needs at least one L1 term")
        return out.mul_(self.theta).add_(xi, alpha=2.0 * self.gamma_a).view(bsz * c, 1, h, w)

    def preconditioner(self) -> torch.Tensor:
        """The inverse diagonal of :meth:`matvec`'s operator, ``(B C, 1, H, W)``."""
        bsz, c, h, w = self.rho.shape
        if self._degree is None:
            self._degree = sum(t.normal_diagonal() for t, _ in self.terms)
        diag: torch.Tensor = 2.0 * self.gamma_a + self.theta * self._degree
        return (1.0 / diag).expand(bsz, c, h, w).reshape(bsz * c, 1, h, w)

    def retune(self, theta: float, g_adj: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """Move to penalty ``theta`` keeping the multipliers (:func:`change_penalty`)."""
        new_lams = [g / theta for _, g in self.terms]
        ratio = theta / self.theta
        rhs = change_penalty(
            rhs, self.data_rhs, g_adj, self.states, self.terms, self.lams, new_lams, ratio
        )
        self.theta, self.lams = theta, new_lams
        return rhs


def change_penalty(
    rhs: torch.Tensor,
    data_rhs: torch.Tensor,
    g_adj: torch.Tensor,
    states: list[Any],
    active_terms: Sequence[tuple[Any, float]],
    lams: Sequence[float],
    new_lams: Sequence[float],
    ratio: float,
) -> torch.Tensor:
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
