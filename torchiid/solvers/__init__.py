"""Linear and L1 solvers: batched PCG, Split-Bregman, multigrid preconditioners."""

from torchiid.solvers.multigrid import (
    AMGPreconditioner,
    AnchoredSystem,
    GalerkinMultigrid,
    HSCPreconditioner,
    PCGHistory,
    StencilOperator,
    anchored_system,
    assemble_csr,
    pcg_callable,
)

__all__ = [
    "AMGPreconditioner",
    "AnchoredSystem",
    "GalerkinMultigrid",
    "HSCPreconditioner",
    "PCGHistory",
    "StencilOperator",
    "anchored_system",
    "assemble_csr",
    "pcg_callable",
]
