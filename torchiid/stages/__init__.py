"""The two stages of the decomposition (paper §3.2-3.3).

Each stage takes its problem (the tensors: :class:`ShadingProblem`, :class:`ReflectanceProblem`)
and its parameter group (:class:`~torchiid.params.ShadingParameters`,
:class:`~torchiid.params.ReflectanceParameters`, e.g. ``params.alternation(k)``). The 0.x
configuration objects ``ShadingWeights``, ``ShadingOptions``, ``ReflectanceWeights`` and
``ReflectanceOptions`` were removed in 1.2.0: reading one raises an ``ImportError`` naming its
replacement.
"""

from typing import Any

from torchiid.stages.config import (
    ReflectanceProblem,
    ShadingProblem,
    TemporalPrior,
    removed_attribute,
)
from torchiid.stages.reflectance import (
    ReflectanceCache,
    ReflectanceResult,
    ReflectanceTerms,
    ReflectanceTimings,
    build_reflectance_terms,
    shading_from_ratio,
    solve_reflectance,
)
from torchiid.stages.shading import (
    ShadingDiagnostics,
    ShadingResult,
    ShadingSystem,
    ShadingSystemCache,
    build_shading_system,
    solve_shading,
)

__all__ = [
    "ReflectanceProblem",
    "ShadingProblem",
    "TemporalPrior",
    "ReflectanceCache",
    "ReflectanceResult",
    "ReflectanceTerms",
    "ReflectanceTimings",
    "build_reflectance_terms",
    "shading_from_ratio",
    "solve_reflectance",
    "ShadingDiagnostics",
    "ShadingResult",
    "ShadingSystem",
    "ShadingSystemCache",
    "build_shading_system",
    "solve_shading",
]


def __getattr__(name: str) -> Any:
    raise removed_attribute(__name__, name)
