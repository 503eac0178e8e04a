"""Dense SPD solves for the coarsest level of the hierarchical preconditioners."""

from __future__ import annotations

import torch

__all__ = ["DenseSPD"]


class DenseSPD:
    """Solves with a batch ``(B, n, n)`` of dense symmetric PSD matrices (float64).

    Cholesky; where round-off made a (near-singular) matrix indefinite, a clipped
    eigendecomposition instead (eigenvalues below ``1e-13 * lambda_max`` raised to it), so the
    solve is always an SPD operator.
    """

    def __init__(self, dense: torch.Tensor) -> None:
        dense = 0.5 * (dense + dense.transpose(-1, -2)).to(torch.float64)
        self.chol, info = torch.linalg.cholesky_ex(dense)
        self.eig: tuple[torch.Tensor, torch.Tensor] | None = None
        if bool((info != 0).any()):
            ev, vec = torch.linalg.eigh(dense)
            ev = torch.maximum(ev, ev[..., -1:].abs() * 1e-13)
            self.eig = (vec, 1 / ev)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """``A^{-1} rhs`` for ``rhs`` ``(B, n, k)``."""
        rhs = rhs.to(torch.float64)
        if self.eig is not None:
            vec, inv = self.eig
            return vec @ (inv.unsqueeze(-1) * (vec.transpose(-1, -2) @ rhs))
        return torch.cholesky_solve(rhs, self.chol)
