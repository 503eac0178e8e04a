"""Stage 0 semantic features: CNN patch features ``f_b`` (paper §3.1.1)."""

from torchiid.features.backbone import (
    EfficientNetLite0,
    FeatureMapExtractor,
    efficientnet_lite0,
    normalize,
    preprocess,
)
from torchiid.features.onnx_backend import (
    OnnxFeatureExtractor,
    default_cache_dir,
    ensure_onnx_model,
    export_feature_extractor,
    export_to_dir,
)
from torchiid.features.patches import (
    PatchFeatureExtractor,
    PatchFeatures,
    PatchGrid,
    patch_features,
    patch_grid,
)
from torchiid.features.roi import RoIAlign, roi_align

__all__ = [
    "EfficientNetLite0",
    "FeatureMapExtractor",
    "OnnxFeatureExtractor",
    "PatchFeatureExtractor",
    "PatchFeatures",
    "PatchGrid",
    "RoIAlign",
    "default_cache_dir",
    "efficientnet_lite0",
    "ensure_onnx_model",
    "export_feature_extractor",
    "export_to_dir",
    "normalize",
    "patch_features",
    "patch_grid",
    "preprocess",
    "roi_align",
]
