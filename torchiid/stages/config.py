"""What each stage solves: the tensors of its problem (not its configuration).

Each stage takes its **problem** — the tensors (:class:`ShadingProblem`,
:class:`ReflectanceProblem`, with a video's :class:`TemporalPrior`) — and its **parameter
group** (:class:`~torchiid.params.ShadingParameters`,
:class:`~torchiid.params.ReflectanceParameters`), which holds the weights, switches, constants
and solver settings; :meth:`Parameters.alternation <torchiid.params.Parameters.alternation>`
gives the groups of each alternation (§3.4).

``ShadingWeights``, ``ShadingOptions``, ``ReflectanceWeights`` and ``ReflectanceOptions``, the
configuration objects of torchiid 0.x, were removed in 1.2.0: reading one from
:mod:`torchiid.stages` or from here raises an ``ImportError`` naming the group that replaces it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

import torch

from torchiid.core.exceptions import ParameterError

# REMOVED, check_group and removed_attribute serve the stage modules, not users
__all__ = ["ShadingProblem", "ReflectanceProblem", "TemporalPrior", "TEMPORAL_NORMS"]

#: the two forms of the temporal reflectance term (:class:`TemporalPrior`)
TEMPORAL_NORMS = ("l2", "l1")

#: the stages' configuration objects of torchiid 0.x, removed in 1.2.0 -> what replaces each
REMOVED = {
    "ShadingWeights": "torchiid.params.ShadingParameters (params.shading; its .weights())",
    "ShadingOptions": "torchiid.params.ShadingParameters (params.shading)",
    "ReflectanceWeights": (
        "torchiid.params.ReflectanceParameters (params.reflectance; its .weights())"
    ),
    "ReflectanceOptions": "torchiid.params.ReflectanceParameters (params.reflectance)",
}

_G = TypeVar("_G")


@dataclass(frozen=True, eq=False)
class ShadingProblem:
    """The tensors of one shading solve (Eq. 1), linear RGB.

    Attributes:
        image: ``(B, 3, H, W)`` the image ``I`` (``>= 0``).
        patch_centers: ``(P, 2)`` or ``(B, P, 2)`` integer ``(y, x)`` patch centres for ``S_c``.
        patch_features: ``(B, P, D)`` patch descriptors ``f_b`` for ``S_c``.
        similarity: ``(B, 4, H, W)`` proposal similarities ``<g_i, g_j>`` on the 3x3 stencil
            for ``S_m``.
        base_image: ``(B, 3, H, W)`` the previous reflectance, from which the base of the
            matting Laplacian ``S_p`` is made (``ShadingParameters.base_mix``); ``None``: the
            Gaussian-smoothed image is the base.
        mask: ``(B, 1, H, W)`` bool region to decompose, or ``None``.
        texture: ``(B, 1, H, W)`` the texture confidence of ``S_l``'s targets
            (:func:`~torchiid.priors.texture.texture_confidence`) made at the working
            resolution and area-averaged to this size; ``None``: made from ``image`` when
            ``t_x > 0``.

    A prior whose tensors are ``None`` is off whatever its weight.
    """

    image: torch.Tensor
    patch_centers: torch.Tensor | None = None
    patch_features: torch.Tensor | None = None
    similarity: torch.Tensor | None = None
    base_image: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    texture: torch.Tensor | None = None

    def replace(self, **changes: object) -> ShadingProblem:
        """A copy with some tensors changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class TemporalPrior:
    """A reflectance target from another frame of a video: Stage 2 pulls ``z`` toward it.

    Stage 2's energy (Eq. 12) gains a term on the pixels where the target is trusted:

    * ``norm="l2"`` (an anchor): ``s·γ_a·weight · Σ_i c_i ‖z_i − κ T_i‖²``;
    * ``norm="l1"`` (inside Split-Bregman, like ``A``, ``B``, ``C``):
      ``s·γ_a·weight · Σ_i c_i ‖z_i − κ T_i‖₁``,

    with ``c`` the confidence, ``s·γ_a`` the data term's weight (``value_scale · γ_a``, so the
    term follows the §3.4 schedule of the data term) and ``κ`` a global factor per image fitted
    to the current ``ρ`` (the median of ``Σ_c ρ / Σ_c T`` over the trusted pixels): the
    target's scale does not matter, as ``ρ``'s is arbitrary (with ``sigma > 0`` the target is
    ``ρ`` times the smoothed ratio instead, see ``sigma``). For the anchor, ``weight`` is
    the ratio of the anchor to the data term (``weight = 4``: without the sparsity terms
    ``z = (ρ + 4 κT) / 5``); for the L1 form, ``z`` snaps to ``κ T`` wherever
    ``|ρ − κT| ≤ weight / 2`` (per channel, without the sparsity terms) and follows ``ρ``
    beyond, so a wrong target (a flow error that passed the occlusion check, a new object)
    pulls with bounded force.

    Attributes:
        target: ``(B, 3, H, W)`` linear reflectance of the other frame, warped onto this one.
        confidence: ``(B, 1, H, W)`` in ``[0, 1]``: 1 where the target is trusted (the
            flow's forward–backward check passed), 0 where it is not (occluded, outside).
        weight: the term's weight relative to the data term, ``>= 0`` (0: off).
        norm: ``"l2"`` or ``"l1"``.
        sigma: ``0``: the target is ``κ T`` as it is. ``> 0``: only its levels are kept,
            smoothed over ``sigma`` px, and the detail is the current ``ρ``'s:
            ``ρ · exp(G_σ ∗ log(Σ_c T / Σ_c ρ))`` on the trusted pixels
            (:func:`~torchiid.stages.reflectance.temporal_term`). A warped target is blurred
            and shifted a little at its edges (resampling, flow error); frame after frame,
            that would accumulate.
    """

    target: torch.Tensor
    confidence: torch.Tensor
    weight: float = 4.0
    norm: str = "l2"
    sigma: float = 0.0

    def __post_init__(self) -> None:
        if self.norm not in TEMPORAL_NORMS:
            raise ParameterError(
                f"temporal norm must be one of {', '.join(TEMPORAL_NORMS)}, got {self.norm!r}"
            )
        if not self.weight >= 0:
            raise ParameterError(f"temporal weight must be >= 0, got {self.weight}")
        if not self.sigma >= 0:
            raise ParameterError(f"temporal sigma must be >= 0, got {self.sigma}")

    def replace(self, **changes: object) -> TemporalPrior:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class ReflectanceProblem:
    """The tensors of one reflectance solve (Eq. 12), linear RGB.

    Attributes:
        rho: ``(B, 3, H, W)`` the Stage 1 reflectance ``ρ = I / σ`` (``>= 0``).
        image: ``(B, 3, H, W)`` the image ``I``.
        gpca: ``(B, d, H, W)`` PCA-reduced proposal features ``g̊`` for ``B``.
        segments: ``(B, H, W)`` long segment labels giving the representatives of ``C``.
        mask: ``(B, 1, H, W)`` bool region to decompose, or ``None``.
        temporal: a :class:`TemporalPrior` (video: the previous frame's reflectance warped
            onto this one), or ``None`` (a still image: Eq. 12 unchanged).

    A prior whose tensors are ``None`` is off whatever its weight.
    """

    rho: torch.Tensor
    image: torch.Tensor
    gpca: torch.Tensor | None = None
    segments: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    temporal: TemporalPrior | None = None

    def replace(self, **changes: object) -> ReflectanceProblem:
        """A copy with some tensors changed."""
        return dataclasses.replace(self, **changes)


def check_group(function: str, group: object, cls: type[_G], attribute: str) -> _G:
    """``group``, the parameter group the stage function ``function`` takes (a ``cls``).

    Raises:
        ParameterError: ``group`` is not a ``cls``; the message names the class and the
            attribute of :class:`~torchiid.params.Parameters` that holds it.
    """
    if not isinstance(group, cls):
        raise ParameterError(
            f"{function} takes a torchiid.params.{cls.__name__} (params.{attribute}), "
            f"got {type(group).__name__}"
        )
    return group


def removed_attribute(module: str, name: str) -> Exception:
    """What reading a missing ``name`` from ``module`` raises.

    An ``ImportError`` naming the replacement for a name of :data:`REMOVED` (so that
    ``from torchiid.stages import ShadingOptions`` says it, too), else the usual
    ``AttributeError``.
    """
    if name in REMOVED:
        return ImportError(f"{name} was removed in 1.2.0; use {REMOVED[name]}", name=module)
    return AttributeError(f"module {module!r} has no attribute {name!r}")


def __getattr__(name: str) -> Any:
    raise removed_attribute(__name__, name)
