"""Video: temporally consistent decompositions of frame sequences.

:class:`VideoDecomposer` decomposes frames one after another, each tied to the previous one by
optical flow (:mod:`torchiid.video.flow`): the warped previous reflectance is the warm start
of both stages and the target of a temporal term in Stage 2 (:mod:`torchiid.video.temporal`,
:mod:`torchiid.video.linking`); :class:`VideoOptions` (:mod:`torchiid.video.options`) says how.
"""

from torchiid.video.flow import estimate_flow, occlusion_mask, resize_flow, warp
from torchiid.video.options import DEFAULT_TEMPORAL_WEIGHT, VideoOptions
from torchiid.video.temporal import VideoDecomposer, VideoFrame

__all__ = [
    "estimate_flow",
    "occlusion_mask",
    "resize_flow",
    "warp",
    "DEFAULT_TEMPORAL_WEIGHT",
    "VideoDecomposer",
    "VideoFrame",
    "VideoOptions",
]
