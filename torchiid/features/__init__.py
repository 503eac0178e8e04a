"""Stage 0 semantic features.

CNN patch features ``f_b`` (paper §3.1.1) and selective-search mid-level features ``g_i``
(paper §3.1.2).
"""

from torchiid.features.backbone import (
    EfficientNetLite0,
    FeatureMapExtractor,
    efficientnet_lite0,
    normalize,
    preprocess,
)
from torchiid.features.midlevel import (
    MidLevelBatch,
    MidLevelFeatures,
    midlevel_features,
    midlevel_features_batch,
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
    release_feature_extractors,
)
from torchiid.features.proposals import COLOUR_SPACES, Proposals, Strategy, selective_search
from torchiid.features.roi import RoIAlign, roi_align
from torchiid.features.semantic import SemanticFeatures, semantic_features
from torchiid.features.visualize import draw_patch_grid, overlay_masks, pca_image, select_masks

__all__ = [
    "COLOUR_SPACES",
    "MidLevelBatch",
    "MidLevelFeatures",
    "Proposals",
    "SemanticFeatures",
    "Strategy",
    "draw_patch_grid",
    "midlevel_features",
    "midlevel_features_batch",
    "overlay_masks",
    "pca_image",
    "select_masks",
    "selective_search",
    "semantic_features",
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
    "release_feature_extractors",
    "roi_align",
]
