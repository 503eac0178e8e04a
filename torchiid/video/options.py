"""How the frames of a video are tied together: :class:`VideoOptions`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from torchiid.core.exceptions import ParameterError
from torchiid.stages.config import TEMPORAL_NORMS
from torchiid.video.flow import FLOW_METHODS

__all__ = ["DEFAULT_TEMPORAL_WEIGHT", "VideoOptions"]

#: default weight of the temporal term per norm (relative to Stage 2's data term)
DEFAULT_TEMPORAL_WEIGHT = {"l2": 4.0, "l1": 1.0}


@dataclass(frozen=True)
class VideoOptions:
    """How frames are tied together (see :mod:`torchiid.video.temporal`).

    Attributes:
        temporal_norm: ``"l2"`` (anchor) or ``"l1"`` (Split-Bregman term).
        temporal_weight: weight of the temporal term relative to Stage 2's data term
            (``None``: :data:`DEFAULT_TEMPORAL_WEIGHT` of the norm; 0: no temporal term).
        warm_start: start both stages of frame ``t`` from the warped previous reflectance.
        init_median: side of the median filter applied to the warm start's log-shading
            ``log(Σ I / Σ T)`` (1 or 0: none). The warped reflectance's edges are a little
            blurred and shifted (resampling, flow error), so dividing the sharp new frame by it
            leaves thin ridges along every edge; solved from there with capped iterations,
            they would stay in the shading and accumulate frame after frame. A 3×3 median
            removes ridges of a pixel or two and keeps the shading's own edges.
        target_sigma: ``> 0``: the temporal target keeps only the warped reflectance's levels,
            smoothed over this many working-resolution px, and the current ``ρ``'s detail
            (:class:`~torchiid.stages.config.TemporalPrior` ``sigma``); 0 (default): the
            warped reflectance as it is.
        later_iterations: alternations of a warm-started frame: the last ``later_iterations``
            of the §3.4 schedule (``decompose(..., schedule_start=)``); 0: all
            ``params.iterations``.
        match_scale: one albedo scale for the sequence (else each frame's own quantile).
        reuse_features: warp the previous frame's Stage 0 features when the scene moved little.
        reuse_max_motion: 90th percentile of the flow's length (working-resolution px) up to
            which features are reused.
        reuse_min_trusted: share of trusted pixels (of those inside both frames' masks)
            needed to reuse features.
        reuse_max_frames: features are recomputed at least every ``reuse_max_frames + 1``
            frames.
        flow: ``"dis"`` or ``"farneback"`` (:func:`~torchiid.video.flow.estimate_flow`).
        flow_max_side: the flow is estimated on the frames brought to this longer side
            (0: full resolution), then resized to the working resolution; finer than the
            working resolution because the flow's error, not its cost, limits the temporal
            term.
        occlusion_alpha: relative tolerance of the forward–backward check.
        occlusion_beta: absolute tolerance (px² at the flow's resolution).
    """

    temporal_norm: str = "l2"
    temporal_weight: float | None = None
    warm_start: bool = True
    later_iterations: int = 2
    init_median: int = 3
    target_sigma: float = 0.0
    match_scale: bool = True
    reuse_features: bool = True
    reuse_max_motion: float = 4.0
    reuse_min_trusted: float = 0.8
    reuse_max_frames: int = 4
    flow: str = "dis"
    flow_max_side: int = 1024
    occlusion_alpha: float = 0.01
    occlusion_beta: float = 0.5

    def __post_init__(self) -> None:
        if self.temporal_norm not in TEMPORAL_NORMS:
            raise ParameterError(
                f"temporal norm must be one of {', '.join(TEMPORAL_NORMS)}, "
                f"got {self.temporal_norm!r}"
            )
        if self.temporal_weight is not None and not self.temporal_weight >= 0:
            raise ParameterError(f"temporal weight must be >= 0, got {self.temporal_weight}")
        if self.flow not in FLOW_METHODS:
            raise ParameterError(
                f"flow method must be one of {', '.join(FLOW_METHODS)}, got {self.flow!r}"
            )
        if self.init_median < 0 or self.init_median > 1 and self.init_median % 2 == 0:
            raise ParameterError(f"init_median must be 0, 1 or odd, got {self.init_median}")
        if not self.target_sigma >= 0:
            raise ParameterError(f"target_sigma must be >= 0, got {self.target_sigma}")
        if self.later_iterations < 0:
            raise ParameterError(f"later_iterations must be >= 0, got {self.later_iterations}")
        if self.reuse_max_frames < 0 or not self.reuse_max_motion >= 0:
            raise ParameterError("reuse_max_frames and reuse_max_motion must be >= 0")

    @property
    def weight(self) -> float:
        """The temporal weight in use."""
        if self.temporal_weight is None:
            return DEFAULT_TEMPORAL_WEIGHT[self.temporal_norm]
        return float(self.temporal_weight)

    @property
    def linked(self) -> bool:
        """Whether frames are tied at all (else every frame is a still decomposition)."""
        return self.weight > 0 or self.warm_start or self.match_scale or self.reuse_features

    @classmethod
    def frame_by_frame(cls) -> VideoOptions:
        """Every frame decomposed on its own, exactly as ``decompose`` does (the baseline)."""
        return cls(temporal_weight=0.0, warm_start=False, match_scale=False, reuse_features=False)

    def replace(self, **changes: object) -> VideoOptions:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)
