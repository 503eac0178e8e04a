"""torchiid: intrinsic image decomposition (``I = R · S``) with semantic hierarchical priors.

A PyTorch implementation of Saini & Narayanan, "Semantic Hierarchical Priors for Intrinsic
Image Decomposition" (IJCV). Images are channel-first **linear** RGB tensors ``(B, 3, H, W)``.

>>> import torchiid
>>> from torchiid.synthetic import mondrian
>>> img = mondrian(64, 64).image
>>> out = torchiid.decompose(img, torchiid.Parameters().replace(iterations=1))
>>> out.reflectance.shape, out.shading.shape
(torch.Size([1, 3, 64, 64]), torch.Size([1, 1, 64, 64]))
"""

# first: before anything imports torch (see the module)
import torchiid.openmp  # noqa: F401

from torchiid import edit
from torchiid.baselines.retinex import ColorRetinex, color_retinex
from torchiid.core.exceptions import (
    ConvergenceWarning,
    ImageError,
    MemoryLimitError,
    ModelError,
    ParameterError,
    ShapeError,
    TorchiidError,
)
from torchiid.eval import dssim, local_mse, mit_lmse, saw_ap, si_mse, whdr
from torchiid.features import (
    MidLevelFeatures,
    PatchFeatures,
    Proposals,
    SemanticFeatures,
    efficientnet_lite0,
    midlevel_features,
    patch_features,
    patch_grid,
    selective_search,
    semantic_features,
)
from torchiid.io import load_image, load_mask, save_image
from torchiid.losses import PriorLoss, image_priors
from torchiid.model import Decomposition, IntrinsicDecomposer, IterationLayers, decompose
from torchiid.params import Parameters
from torchiid.solvers.pcg import PCGResult, pcg
from torchiid.solvers.split_bregman import SplitBregmanResult, split_bregman
from torchiid.stages import ReflectanceResult, ShadingResult, solve_reflectance, solve_shading

__version__ = "0.1.0"

__all__ = [
    "ColorRetinex",
    "ConvergenceWarning",
    "Decomposition",
    "ImageError",
    "IntrinsicDecomposer",
    "IterationLayers",
    "MemoryLimitError",
    "MidLevelFeatures",
    "ModelError",
    "PCGResult",
    "Parameters",
    "ParameterError",
    "PatchFeatures",
    "PriorLoss",
    "Proposals",
    "ReflectanceResult",
    "SemanticFeatures",
    "ShadingResult",
    "ShapeError",
    "SplitBregmanResult",
    "TorchiidError",
    "color_retinex",
    "decompose",
    "edit",
    "dssim",
    "efficientnet_lite0",
    "image_priors",
    "load_image",
    "load_mask",
    "local_mse",
    "midlevel_features",
    "mit_lmse",
    "patch_features",
    "patch_grid",
    "pcg",
    "save_image",
    "saw_ap",
    "selective_search",
    "semantic_features",
    "si_mse",
    "solve_reflectance",
    "solve_shading",
    "split_bregman",
    "whdr",
]
