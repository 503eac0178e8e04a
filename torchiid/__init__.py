"""torchiid: intrinsic image decomposition (``I = R · S``) with semantic hierarchical priors.

A PyTorch implementation of Saini & Narayanan, "Semantic Hierarchical Priors for Intrinsic
Image Decomposition" (IJCV). Images are channel-first **linear** RGB tensors ``(B, 3, H, W)``.

>>> import torchiid
>>> from torchiid.synthetic import mondrian
>>> img = mondrian(64, 64).image
>>> out = torchiid.decompose(img, torchiid.Parameters().replace(iterations=1))
>>> out.reflectance.shape, out.shading.shape
(torch.Size([1, 3, 64, 64]), torch.Size([1, 1, 64, 64]))

The names below are loaded on first use (PEP 562), so ``import torchiid`` and the command
line's ``--help`` do not load torch; ``from torchiid import decompose`` loads what
``decompose`` needs.
"""

# first: before anything imports torch (see the module)
import torchiid.openmp  # noqa: F401

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

from torchiid._version import __version__ as __version__

if TYPE_CHECKING:  # what static tools (mypy, mkdocstrings) see; at run time: __getattr__
    from torchiid import edit
    from torchiid.baselines.retinex import ColorRetinex, color_retinex
    from torchiid.core.exceptions import (
        ConvergenceWarning,
        ImageError,
        InputWarning,
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

__all__ = [
    "ColorRetinex",
    "ConvergenceWarning",
    "Decomposition",
    "ImageError",
    "InputWarning",
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

#: the module each public name is defined in (or re-exported by); ``edit`` is a module itself
_SOURCES = {
    "ColorRetinex": "torchiid.baselines.retinex",
    "color_retinex": "torchiid.baselines.retinex",
    **dict.fromkeys(
        [
            "ConvergenceWarning",
            "ImageError",
            "InputWarning",
            "MemoryLimitError",
            "ModelError",
            "ParameterError",
            "ShapeError",
            "TorchiidError",
        ],
        "torchiid.core.exceptions",
    ),
    **dict.fromkeys(
        ["dssim", "local_mse", "mit_lmse", "saw_ap", "si_mse", "whdr"], "torchiid.eval"
    ),
    **dict.fromkeys(
        [
            "MidLevelFeatures",
            "PatchFeatures",
            "Proposals",
            "SemanticFeatures",
            "efficientnet_lite0",
            "midlevel_features",
            "patch_features",
            "patch_grid",
            "selective_search",
            "semantic_features",
        ],
        "torchiid.features",
    ),
    **dict.fromkeys(["load_image", "load_mask", "save_image"], "torchiid.io"),
    **dict.fromkeys(["PriorLoss", "image_priors"], "torchiid.losses"),
    **dict.fromkeys(
        ["Decomposition", "IntrinsicDecomposer", "IterationLayers", "decompose"], "torchiid.model"
    ),
    "Parameters": "torchiid.params",
    **dict.fromkeys(["PCGResult", "pcg"], "torchiid.solvers.pcg"),
    **dict.fromkeys(["SplitBregmanResult", "split_bregman"], "torchiid.solvers.split_bregman"),
    **dict.fromkeys(
        ["ReflectanceResult", "ShadingResult", "solve_reflectance", "solve_shading"],
        "torchiid.stages",
    ),
}


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use (PEP 562) and keep the name here.

    A subpackage or module (``torchiid.io``, ``torchiid.model``, ...) is imported on first
    access too, as if the package had imported it.
    """
    if name in _SOURCES:
        value = getattr(importlib.import_module(_SOURCES[name]), name)
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later lookups do not come here
    return value


def __dir__() -> list[str]:
    """The module's names, the public ones not yet loaded included."""
    return sorted(set(globals()) | set(__all__))
