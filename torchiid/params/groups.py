"""The parameter groups of Stage 0 (semantic features) and of the outputs."""

import dataclasses

from torchiid.core.exceptions import ParameterError
from torchiid.params.fields import ParameterGroup, param

__all__ = ["FeatureParameters", "OutputParameters"]


@dataclasses.dataclass(frozen=True)
class FeatureParameters(ParameterGroup):
    """Stage 0: the semantic features the priors are built from (paper §3.1).

    :func:`~torchiid.features.semantic.semantic_features` reads these; what a switched-off
    prior does not need is not computed.
    """

    patch_size: int = param(
        60, "side of the square patches the CNN describes (px)", paper=60, valid="> 0"
    )
    patch_stride: int = param(
        30,
        "stride of the patch grid (px)",
        paper=30,
        valid="> 0; at most patch_size, else pixels are left uncovered",
    )
    feature_mode: str = param(
        "shared",
        "how the patches are described: 'shared' (one CNN pass, RoI-aligned patch features) "
        "or 'crop' (one CNN pass per cropped patch)",
        paper="crop",
        valid="one of shared, crop",
        why="'shared': one CNN pass for every patch of the image instead of one per patch",
    )
    feature_backend: str = param(
        "onnx", "runtime of the CNN: 'onnx' (onnxruntime) or 'torch'", valid="one of onnx, torch"
    )
    lle_features: str = param(
        "cnn",
        "patch descriptor f_b of S_c: 'cnn' (the CNN's) or 'rgb' (patch mean colour, Table 2)",
        paper="cnn",
        valid="one of cnn, rgb",
    )
    proposal_pca_dim: int = param(
        8, "dimension of the PCA-reduced mid-level feature g̊ of Stage 2's B", valid="> 0"
    )
    segment_scale: float = param(
        200.0,
        "Felzenszwalb scale of the segments whose representative pixels form Q (Stage 2's C)",
        valid="> 0",
    )

    def _check(self) -> None:
        if self.patch_stride > self.patch_size:
            raise ParameterError(
                f"patch_stride ({self.patch_stride}) larger than patch_size ({self.patch_size}) "
                "leaves pixels uncovered"
            )


@dataclasses.dataclass(frozen=True)
class OutputParameters(ParameterGroup):
    """The working resolution and the full-resolution layers.

    :func:`~torchiid.model.full_resolution_layers` brings the working-resolution shading back
    to the input's resolution with a guided filter and sets the scale of ``R · S``.
    """

    max_side: int = param(
        512,
        "images whose longer side exceeds this are decomposed at this size and the layers "
        "brought back to full resolution edge-aware (0: never resize)",
        valid=">= 0",
        why="512, not the 384 that scores best on MIT's single objects: photos hold more and "
        "smaller things (Large photos, Choosing the working resolution)",
    )
    guide_radius: int = param(
        2,
        "box radius (working-resolution px) of the guided filter that upsamples the log-shading",
        valid="> 0",
    )
    guide_eps: float = param(
        1e-3,
        "regulariser of that guided filter (squared log-luminance units)",
        valid="> 0",
    )
    albedo_quantile: float = param(
        0.999,
        "this quantile of the per-pixel maximum reflectance channel is 1 (an albedo in [0, 1]); "
        "pixels above it move their excess into the shading",
        valid="in (0, 1]",
    )
    view_quantile: float = param(
        0.99,
        "quantile of the shading shown as white in the viewable shading PNG (shading_white)",
        valid="in (0, 1]",
    )
