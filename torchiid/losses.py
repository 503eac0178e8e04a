"""The method's priors as differentiable training losses for learned decomposition networks.

A network predicts ``(R, S)`` (or their logs) for linear RGB images ``I``. The priors' weights
are derived from the image alone (and its Stage 0 features) and computed **without gradient**
(:func:`image_priors`, under ``torch.no_grad``); only the predicted layers carry gradient:

* shading (Eq. 1): ``Σ_t λ_t E_t(s)`` with ``s = log S`` and
  ``E_t(s) = sᵀ L_t s − 2 b_tᵀ s + c_t = Σ_r w_r ((M s)_r − c_r)²`` for ``S_c`` (Eq. 2),
  ``S_p`` (Eq. 3), ``S_m`` (Eq. 4), ``S_l`` (Eq. 5) and, when ``lambda_s > 0``, ``S_s`` (plain
  smoothness, not in the paper) -- :func:`shading_losses`;
* reflectance (Eq. 12): ``Σ_k γ_k ‖W_k M_k R‖₁`` for ``A`` (local, Eq. 8), ``B`` (mid-level,
  Eq. 9), ``C`` (global, Eq. 10) -- :func:`reflectance_losses`; the colour weights are
  computed on ``ρ`` = the image (the solver's first alternation uses the Stage 1 ``ρ``);
* reconstruction: ``‖R · S − I‖²`` -- :func:`reconstruction_loss`.

:class:`PriorLoss` combines them with the paper's weights: ``λ`` and ``γ`` of
:class:`~torchiid.params.Parameters` at one alternation, and the reconstruction weighted like
Eq. 12's data term on ``[0, 1]`` values, ``γ_a · value_scale`` (255). Every energy is divided by
the number of pixels ``H·W`` and averaged over the batch, so the scale does not depend on the
crop size. Everything follows the device and dtype of the image (float32 for a float16 or
bfloat16 one: layers from a mixed-precision network are evaluated in the priors' dtype).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import nn

from torchiid.core.check import as_mask, check_same_batch
from torchiid.core.compiling import eager_under_compile
from torchiid.core.exceptions import ShapeError
from torchiid.features.semantic import SemanticFeatures, semantic_features
from torchiid.params import Parameters
from torchiid.pipeline.inputs import check_inputs
from torchiid.priors.api import ReflectancePrior, ShadingPrior, reflectance_priors, shading_priors
from torchiid.stages.reflectance import build_reflectance_terms
from torchiid.stages.shading import build_shading_system

__all__ = [
    "ImagePriors",
    "PriorLoss",
    "image_priors",
    "reconstruction_loss",
    "reflectance_losses",
    "shading_losses",
]


@dataclass(frozen=True)
class ImagePriors:
    """Every active prior of a batch of images, built separately.

    Attributes:
        shading: name (``"S_c"``, ``"S_p"``, ``"S_m"``, ``"S_l"``, ``"S_s"``) ->
            :class:`~torchiid.priors.api.ShadingPrior`.
        reflectance: name (``"A"``, ``"B"``, ``"C"``; ``"A+B"`` when built with
            ``merge=True``) -> :class:`~torchiid.priors.api.ReflectancePrior`.
        shape: ``(B, H, W)``.
        dtype: the dtype the priors hold (the image's; float32 for a float16 or bfloat16
            image). :class:`PriorLoss` evaluates the layers in it.
    """

    shading: dict[str, ShadingPrior]
    reflectance: dict[str, ReflectancePrior]
    shape: tuple[int, int, int]
    dtype: torch.dtype = torch.float32


@torch.no_grad()
def image_priors(
    image: torch.Tensor,
    params: Parameters | None = None,
    *,
    features: SemanticFeatures | None = None,
    mask: torch.Tensor | None = None,
    alternation: int = 1,
    rho: torch.Tensor | None = None,
    base_image: torch.Tensor | None = None,
    merge: bool = False,
) -> ImagePriors:
    """Build each prior of the method for a batch of images, without gradient.

    The builders are the stages' own (:func:`~torchiid.stages.shading.build_shading_system`,
    :func:`~torchiid.stages.reflectance.build_reflectance_terms`), so the terms are exactly the
    solver's, unweighted and unmerged (``A`` and ``B`` separate unless ``merge``).

    Args:
        image: ``(B, 3, H, W)`` or ``(3, H, W)`` linear RGB at the resolution the priors
            should act on, checked as :func:`~torchiid.decompose` checks it; a float16 or
            bfloat16 image gives float32 priors.
        params: weights, switches and constants (default :class:`~torchiid.params.Parameters`).
        features: Stage 0 features of ``image`` (computed when ``None``).
        mask: optional mask (nonzero inside); pairs and rows touching the outside are dropped.
        alternation: 1-based alternation whose weights (§3.4 schedule) to report.
        rho: the reflectance the colour weights of ``A``, ``B``, ``C`` are computed on
            (default: the image itself).
        base_image: the previous reflectance, from which the matting base of ``S_p`` is made
            as in the solver's later alternations (mixed with the smoothed image by
            ``params.shading.base_mix``; 1 uses it as the base itself); default: the
            Gaussian-smoothed image.
        merge: build ``A`` and ``B`` as the solver's merged term ``"A+B"``.

    Returns:
        :class:`ImagePriors`.
    """
    params = params if params is not None else Parameters()
    image, msk = check_inputs(image, mask, params)
    if image.dtype in (torch.float16, torch.bfloat16):
        image = image.float()  # the priors' kernels work in float32 or float64
    if features is None:
        features = semantic_features(image, params)
    shading, reflectance = params.alternation(alternation)
    sh = build_shading_system(
        features.shading_problem(image, base_image=base_image, mask=msk), shading, seed=params.seed
    )
    rt = build_reflectance_terms(
        features.reflectance_problem(image if rho is None else rho, image, mask=msk),
        reflectance,
        merge=merge,
    )
    b, _, h, w = image.shape
    shading_terms, reflectance_terms = shading_priors(sh.terms), reflectance_priors(rt.terms)
    return ImagePriors(shading_terms, reflectance_terms, (b, h, w), image.dtype)


def shading_losses(
    log_shading: torch.Tensor, priors: Mapping[str, ShadingPrior]
) -> dict[str, torch.Tensor]:
    """Unweighted energies ``E_t(s)`` of the shading priors, name -> ``(B,)``.

    Shape:
        log_shading ``(B, 1, H, W)``.
    """
    return {name: p.energy(log_shading) for name, p in priors.items()}


def reflectance_losses(
    reflectance: torch.Tensor, priors: Mapping[str, ReflectancePrior]
) -> dict[str, torch.Tensor]:
    """Unweighted L1 sparsity ``‖W M R‖₁`` (summed over channels), name -> ``(B,)``.

    Shape:
        reflectance ``(B, C, H, W)`` (linear, as in Eq. 12).
    """
    return {name: p.l1(reflectance) for name, p in priors.items()}


def reconstruction_loss(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """``‖R · S − I‖²`` per image (inside the mask), ``(B,)``.

    Shape:
        image, reflectance ``(B, 3, H, W)``; shading ``(B, 1, H, W)`` or ``(B, 3, H, W)``.
    """
    err = (reflectance * shading - image).square()
    if mask is not None:
        err = err * as_mask(mask, image).to(err.dtype)
    return err.flatten(1).sum(1)


class PriorLoss(nn.Module):
    """The method's energy as a loss: reconstruction plus the weighted shading and L1 priors.

    ``loss = mean_b [w_rec ‖R·S − I‖² + Σ_t λ_t E_t(log S) + Σ_k γ_k ‖W_k M_k R‖₁] / (H·W)``.

    Args:
        params: the weights ``λ``, ``γ`` (at ``alternation``), ``γ_a``, ``value_scale`` and the
            priors' constants (default :class:`~torchiid.params.Parameters`).
        alternation: which alternation's weights (§3.4 schedule).
        use_shading: include the shading priors.
        use_reflectance: include the reflectance priors.
        reconstruction_weight: ``w_rec`` (default ``γ_a · value_scale``, Eq. 12's data weight).
        shading_scale: extra factor on the shading priors (default 1).
        reflectance_scale: extra factor on the reflectance priors (default 1).
        log_space: the inputs are ``log R`` and ``log S`` (the network's raw outputs).

    Shape:
        image, reflectance ``(B, 3, H, W)``; shading ``(B, 1, H, W)``; output a scalar.

    Example:
        >>> from torchiid.synthetic import mondrian
        >>> m = mondrian(24, 24, dtype=torch.float64)
        >>> p = Parameters().replace(patch_size=8, patch_stride=4)
        >>> loss = PriorLoss(p)(m.image, m.reflectance, m.shading)
        >>> bool(loss > 0)
        True
    """

    def __init__(
        self,
        params: Parameters | None = None,
        *,
        alternation: int = 1,
        use_shading: bool = True,
        use_reflectance: bool = True,
        reconstruction_weight: float | None = None,
        shading_scale: float = 1.0,
        reflectance_scale: float = 1.0,
        log_space: bool = False,
    ) -> None:
        super().__init__()
        self.params = params if params is not None else Parameters()
        self.alternation = alternation
        self.use_shading = use_shading
        self.use_reflectance = use_reflectance
        r = self.params.reflectance
        self.reconstruction_weight = (
            r.gamma_a * r.value_scale if reconstruction_weight is None else reconstruction_weight
        )
        self.shading_scale = shading_scale
        self.reflectance_scale = reflectance_scale
        self.log_space = log_space

    def priors(
        self,
        image: torch.Tensor,
        features: SemanticFeatures | None = None,
        mask: torch.Tensor | None = None,
    ) -> ImagePriors:
        """The priors of ``image`` (no gradient); cache them for fixed training crops.

        Under ``torch.compile`` they are built as they are, outside the compiled graph.
        """
        return eager_under_compile(image_priors)(
            image, self.params, features=features, mask=mask, alternation=self.alternation
        )

    def components(
        self,
        image: torch.Tensor,
        reflectance: torch.Tensor,
        shading: torch.Tensor,
        priors: ImagePriors | None = None,
        mask: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """Every weighted, per-pixel term, name -> ``(B,)`` (``"reconstruction"`` and priors).

        Layers in another dtype than the priors (float16 or bfloat16 under mixed precision)
        are evaluated in the priors' dtype; the gradient flows back through the conversion.

        Under ``torch.compile`` the terms are taken as they are, outside the compiled graph,
        while the network around them compiles; their gradient reaches the network's layers
        all the same.

        Raises:
            ShapeError: the image, the layers and the priors differ in batch or size.
        """
        return eager_under_compile(self._components)(image, reflectance, shading, priors, mask)

    def _components(self, image, reflectance, shading, priors, mask) -> dict[str, torch.Tensor]:
        check_same_batch(image, reflectance, shading, names=["image", "reflectance", "shading"])
        if priors is None:
            priors = (
                self.priors(image, mask=mask) if self.use_shading or self.use_reflectance else None
            )
        if priors is not None:
            if (image.shape[0], *image.shape[-2:]) != priors.shape:
                b, h, w = priors.shape
                raise ShapeError(
                    f"the priors are of {b} image(s) of {w}x{h} px but image has shape "
                    f"{tuple(image.shape)}"
                )
            dtype = priors.dtype
            image, reflectance, shading = (x.to(dtype) for x in (image, reflectance, shading))
        if self.log_space:
            log_r, log_s = reflectance, shading
            reflectance, shading = log_r.exp(), log_s.exp()
        else:
            log_s = shading.clamp_min(self.params.reflectance.shading_floor).log()
        n = image.shape[-2] * image.shape[-1]
        out = {
            "reconstruction": self.reconstruction_weight
            * reconstruction_loss(image, reflectance, shading, mask)
            / n
        }
        if priors is None:
            return out
        if self.use_shading:
            for name, e in shading_losses(log_s, priors.shading).items():
                out[name] = self.shading_scale * priors.shading[name].weight * e / n
        if self.use_reflectance:
            for name, e in reflectance_losses(reflectance, priors.reflectance).items():
                out[name] = self.reflectance_scale * priors.reflectance[name].weight * e / n
        return out

    def forward(
        self,
        image: torch.Tensor,
        reflectance: torch.Tensor,
        shading: torch.Tensor,
        priors: ImagePriors | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The total loss, a scalar (mean over the batch); see :meth:`components`."""
        return eager_under_compile(self._total)(image, reflectance, shading, priors, mask)

    def _total(self, image, reflectance, shading, priors, mask) -> torch.Tensor:
        parts = self.components(image, reflectance, shading, priors, mask)
        return torch.stack(list(parts.values())).sum(0).mean()
