"""Weighted L1 difference terms ``‖diag(v) M z‖₁`` for Split-Bregman, and the data term.

The reflectance energy (Eq. 6/12) is ``π = γ_l ‖A z‖₁ + γ_m ‖B z‖₁ + γ_g ‖C z‖₁ + γ_a ‖z − ρ‖²``
over the 3-channel linear reflectance ``z``. Every L1 term is a weighted pair-difference operator
``diag(v) M`` applied to each channel separately (anisotropic L1): row ``(i, j)`` of ``M z`` is
``z_i − z_j`` and ``v_ij ∈ [0, 1]`` its weight (Eq. 7).

:class:`L1Term` is the Split-Bregman step shared by the terms; :class:`PairL1Term` holds ``C``,
an arbitrary list of pairs per image (``(B, P)`` indices padded with zero-weight pairs, applied
with ``gather``/``scatter_add``); the stencil terms ``A`` and ``B`` are
:class:`~torchiid.priors.reflectance_terms.StencilL1Term`. Every term's ``matrix()`` is the
operator ``diag(v) M`` as a torch sparse COO matrix (block diagonal over the batch, acting on
one channel), the canonical reference the fast paths are tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.core.exceptions import ParameterError

__all__ = ["BregmanStats", "L1Term", "MeasuredStep", "PairL1Term", "Step", "data_term"]


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


#: what ``bregman_step`` returns: the term's new state (opaque to the solver, which hands it
#: back to the next update), the update's part of the ``z`` step's right-hand side and
#: ``‖W M z‖₁`` (``None`` unless asked for)
Step = tuple[object, torch.Tensor, "torch.Tensor | None"]

#: ``bregman_step(..., stats=True)``: also the update's :class:`BregmanStats`
MeasuredStep = tuple[object, torch.Tensor, torch.Tensor, "BregmanStats"]


def _sums(x: torch.Tensor) -> torch.Tensor:
    return x.flatten(1).sum(dim=1)


class L1Term:
    """Shared Split-Bregman step for a weighted difference operator ``W M``.

    Subclasses provide ``apply`` (``W M z``), ``adjoint`` (``(W M)ᵀ y``), ``normal_matvec``
    (``Mᵀ W² M z``), ``normal_diagonal`` and ``init_state``.
    """

    #: ``bregman_step`` takes ``stats=True`` (:class:`BregmanStats`) and ``rescale_state``
    #: exists: Split-Bregman may stop on the duality gap and change its penalty
    bregman_stats = True

    def apply(self, z: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """``W M z``."""
        raise NotImplementedError

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """``(W M)ᵀ y``."""
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
        *,
        stats: bool = False,
    ) -> Step | MeasuredStep:
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
        if l1 is not None and apply_sq is not None:  # stats
            primal = _sums(b.square() if old is None else (b - old).square_())
            split_sq = _sums((u - b).square_())
            measured = BregmanStats(l1, primal, apply_sq, split_sq, self.adjoint(b))
        rhs = self.adjoint(u.sub_(b).sub_(b))
        return (b, rhs, l1) if measured is None else (b, rhs, measured.l1, measured)

    def rescale_state(
        self, b: torch.Tensor | None, lam: float, new_lam: float
    ) -> torch.Tensor | None:
        """The state ``b`` written at threshold ``lam`` for ``new_lam``: ``b · new_lam / lam``.

        Keeps the dual variable ``b / λ`` (Split-Bregman's penalty ``θ = γ / λ`` changes, the
        Lagrange multiplier ``θ b`` stays). In place; returns the state.
        """
        return None if b is None else b.mul_(new_lam / lam)


class PairL1Term(L1Term):
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
