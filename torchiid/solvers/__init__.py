"""Linear and L1 solvers: batched PCG, Split-Bregman, multigrid preconditioners."""

from torchiid.solvers.amg import AMGPreconditioner
from torchiid.solvers.hsc import HSCPreconditioner
from torchiid.solvers.multigrid import GalerkinMultigrid
from torchiid.solvers.pcg import PCGHistory, pcg_callable
from torchiid.solvers.stencil_operator import StencilOperator
from torchiid.solvers.system import assemble_csr

__all__ = [
    "AMGPreconditioner",
    "GalerkinMultigrid",
    "HSCPreconditioner",
    "PCGHistory",
    "StencilOperator",
    "assemble_csr",
    "pcg_callable",
]
