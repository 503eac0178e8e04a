"""What a decomposition returns: the layers, the parameters used and the solves' reports."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from torchiid.features.semantic import SemanticFeatures
from torchiid.params import Parameters

__all__ = ["IterationLayers", "SolveReport", "Decomposition", "solve_record"]


@dataclass(frozen=True)
class IterationLayers:
    """The layers of one alternation (paper Fig. 5), linear, at the working resolution.

    Each pair is in the output convention (albedo in ``[0, 1]``, see
    :func:`full_resolution_layers`).

    Attributes:
        sigma: ``(B, 1, h, w)`` Stage 1 shading ``σ``.
        rho: ``(B, 3, h, w)`` Stage 1 reflectance ``ρ = I / σ``.
        reflectance: ``(B, 3, h, w)`` Stage 2 reflectance ``R``.
        shading: ``(B, 1, h, w)`` Stage 2 shading ``S`` (gray ``I / R``).
    """

    sigma: torch.Tensor
    rho: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor


@dataclass(frozen=True)
class SolveReport:
    """What one stage's solver did in one alternation (the batch's worst image).

    Attributes:
        stage: ``"shading"`` (PCG on Eq. 1) or ``"reflectance"`` (Split-Bregman on Eq. 12).
        alternation: 1-based alternation.
        iterations: PCG iterations (shading) or outer Bregman iterations (reflectance).
        inner_iterations: CG iterations of all ``z`` steps (reflectance; 0 for shading).
        residual: final relative residual ``‖b − A s‖ / ‖b‖`` (shading) or last relative change
            of ``z`` (reflectance; with ``bregman_gap_tol``, its last relative duality gap).
        tolerance: the stopping tolerance of that measure.
        cap: the iteration cap (PCG iterations or Bregman iterations).
        converged: the measure fell below the tolerance before the cap.
        measure: what ``residual`` is: ``"residual"``, ``"relative change"`` or ``"duality
            gap"``.
        distance: with the duality gap, a certified bound on how far the reflectance ``z`` is
            from Eq. 12's exact minimiser ``z*``: ``‖z − z*‖ / ‖ρ‖`` (the batch's largest; see
            :class:`~torchiid.solvers.split_bregman.SplitBregmanResult`); ``None`` otherwise.
            A solve stopped at its cap was last measured one iterate before the one it
            returns, so its line does not print it.
        size: ``(h, w)`` of the image the solve ran on where it is not the working size (the
            alternations before the last with ``coarse_scale`` below 1), else ``None``.
    """

    stage: str
    alternation: int
    iterations: int
    inner_iterations: int
    residual: float
    tolerance: float
    cap: int
    converged: bool
    measure: str = "residual"
    distance: float | None = None
    size: tuple[int, int] | None = None

    @property
    def capped(self) -> bool:
        """Stopped at its iteration cap before its tolerance (raising the cap may help)."""
        return not self.converged and self.iterations >= self.cap

    def __str__(self) -> str:
        if self.converged:
            state = "converged"
        elif self.capped:
            state = f"stopped at its cap of {self.cap}"
        else:  # a breakdown or no further progress: a larger cap would not help
            state = f"stopped short of its tolerance before its cap of {self.cap} (no progress)"
        within = ""
        if self.distance is not None and self.converged:  # certified for the returned R
            within = f", R within {self.distance:.2%} of the minimiser"
        at = "" if self.size is None else f" (at {self.size[1]}x{self.size[0]})"
        return (
            f"{self.stage} {self.alternation}{at}: {self.iterations} iterations, "
            f"{self.measure} {self.residual:.2g} (tol {self.tolerance:g}){within}, {state}"
        )


@dataclass(frozen=True)
class Decomposition:
    """Result of :func:`~torchiid.model.decompose`; every layer is **linear** RGB / gray.

    Attributes:
        reflectance: ``(B, 3, H, W)`` final reflectance ``R``, an albedo in ``[0, 1]``
            (0 outside the mask), at the input's resolution.
        shading: ``(B, 1, H, W)`` final gray shading ``S`` (0 outside the mask), may exceed 1;
            ``reflectance * shading == image`` inside the mask.
        sigma: ``(B, 1, H, W)`` last Stage 1 shading ``σ`` (same convention as ``shading``),
            or ``None`` when ``decompose(..., return_stage1=False)``.
        rho: ``(B, 3, H, W)`` last Stage 1 reflectance ``ρ = I / σ`` in ``[0, 1]``, or
            ``None``.
        iterations: every alternation's layers if asked for, else an empty tuple.
        params: the parameters used.
        times: seconds per step (``"patch features"``, ``"proposals"``, ...,
            ``"shading k"``, ``"reflectance k"``, ``"total"``).
        mask: ``(B, 1, H, W)`` bool mask used, or ``None``.
        shading_white: ``(B,)`` the shading's ``params.output.view_quantile`` (0.99) quantile inside
            the mask: dividing ``shading`` by it gives a displayable image (the CLI's
            ``-shading.png``), and ``(R · shading_white, S / shading_white)`` is the other
            common convention (bright lit surfaces have shading 1).
        albedo_excess: ``(B,)`` fraction of the pixels inside the mask whose reflectance
            exceeded 1 and had the excess moved into the shading (at most
            ``1 - albedo_quantile`` on the sub-grid the quantile is taken on, so about that
            share of the full image).
        working_size: ``(h, w)`` the resolution the method ran at, height first as in the
            tensors' shapes (``-info.json`` gives sizes as ``[width, height]``).
        solves: one :class:`SolveReport` per stage and alternation.
        features: the Stage 0 features used (at the working resolution) when
            ``decompose(..., return_features=True)``, else ``None``: pass them back as
            ``features=`` to skip Stage 0 (video reuses them across similar frames).
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    sigma: torch.Tensor | None
    rho: torch.Tensor | None
    iterations: tuple[IterationLayers, ...]
    params: Parameters
    times: dict[str, float] = field(default_factory=dict)
    mask: torch.Tensor | None = None
    shading_white: torch.Tensor | None = None
    albedo_excess: torch.Tensor | None = None
    working_size: tuple[int, int] | None = None
    solves: tuple[SolveReport, ...] = ()
    features: SemanticFeatures | None = None

    @property
    def converged(self) -> bool:
        """Whether every solve reached its tolerance."""
        return all(r.converged for r in self.solves)


def solve_record(
    result: Decomposition,
    params: Parameters,
    seconds: float,
    times: dict[str, float] | None = None,
    places: int = 3,
) -> dict[str, Any]:
    """The fields of a ``-info.json`` record that tell how a decomposition went.

    In this order: ``albedo_quantile``, ``albedo_excess`` (the first image's), ``seconds``,
    ``times`` when given (each rounded to ``places`` decimals), ``converged`` and ``solves``
    (the solvers' reports as text).
    """
    record: dict[str, Any] = {
        "albedo_quantile": params.output.albedo_quantile,
        "albedo_excess": float(result.albedo_excess[0]),
        "seconds": round(seconds, 3),
    }
    if times is not None:
        record["times"] = {k: round(v, places) for k, v in times.items()}
    record["converged"] = result.converged
    record["solves"] = [str(r) for r in result.solves]
    return record
