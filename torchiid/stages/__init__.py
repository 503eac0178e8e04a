"""The two stages of the decomposition (paper §3.2-3.3)."""

from torchiid.stages.reflectance import (
    ReflectanceResult,
    ReflectanceTimings,
    shading_from_ratio,
    solve_reflectance,
)
from torchiid.stages.shading import (
    ShadingDiagnostics,
    ShadingResult,
    build_shading_system,
    solve_shading,
)

__all__ = [
    "ReflectanceResult",
    "ReflectanceTimings",
    "shading_from_ratio",
    "solve_reflectance",
    "ShadingDiagnostics",
    "ShadingResult",
    "build_shading_system",
    "solve_shading",
]
