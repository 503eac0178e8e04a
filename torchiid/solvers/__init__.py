"""Linear and L1 solvers: batched PCG, Split-Bregman, multigrid preconditioners."""

from torchiid.solvers.multigrid import (
    AMGPreconditioner,
    GalerkinMultigrid,
    HSCPreconditioner,
    PCGHistory,
    StencilOperator,
    assemble_csr,
    pcg_callable,
)

__all__ = [
    "AMGPreconditioner",
    "GalerkinMultigrid",
    "HSCPreconditioner",
    "PCGHistory",
    "StencilOperator",
    "assemble_csr",
    "pcg_callable",
]
