"""The two stages of the decomposition (paper §3.2-3.3) and their configuration objects."""

from torchiid.stages.config import (
    ReflectanceOptions,
    ReflectanceProblem,
    ReflectanceWeights,
    ShadingOptions,
    ShadingProblem,
    ShadingWeights,
    TemporalPrior,
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
    "ReflectanceOptions",
    "ReflectanceProblem",
    "ReflectanceWeights",
    "ShadingOptions",
    "ShadingProblem",
    "ShadingWeights",
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
