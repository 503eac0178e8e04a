"""The paper's priors: shading quadratics (Eqs. 2-5) and reflectance L1 terms (Eqs. 8-10).

Public objects (see :mod:`torchiid.priors.api`): :class:`ShadingPrior` (quadratic form's matrix
``L``: ``matvec`` and an exact block-diagonal sparse ``to_sparse``), :class:`ReflectancePrior`
(weighted difference operator ``W M``: ``apply`` and ``to_sparse``), and the wrappers
:func:`shading_priors` / :func:`reflectance_priors` of the stages' built terms. To build them
for images use :func:`torchiid.losses.image_priors`.
"""

from torchiid.priors.api import (
    REFLECTANCE_EQUATIONS,
    SHADING_EQUATIONS,
    ReflectancePrior,
    ShadingPrior,
    reflectance_priors,
    shading_priors,
)
from torchiid.priors.quadratic import QuadraticTerm
from torchiid.priors.reflectance_terms import PairL1Term, StencilL1Term
from torchiid.priors.stencil import Stencil

__all__ = [
    "REFLECTANCE_EQUATIONS",
    "SHADING_EQUATIONS",
    "PairL1Term",
    "QuadraticTerm",
    "ReflectancePrior",
    "ShadingPrior",
    "Stencil",
    "StencilL1Term",
    "reflectance_priors",
    "shading_priors",
]
