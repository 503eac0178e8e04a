"""The 3x3 pairwise shading priors ``S_m`` (Eq. 4), ``S_l`` (Eq. 5) and ``S_s`` (not the paper's).

``S_m`` is the mid-level prior, ``S_l`` the local Retinex prior and ``S_s`` plain smoothness. All
three live on the 3x3 half-offset stencil (4 offsets, each unordered neighbour pair once) and are
returned as :class:`~torchiid.priors.quadratic.StencilQuadratic` terms in the log-shading
``s = log sigma``.

* ``S_m = sum_ij w^m_ij (s_i - s_j)^2`` with ``w^m_ij = exp(-(1 - <g_i, g_j>)^2 / t_m^2)``.
* ``S_l = sum_ij w^l_ij ((log p_i - s_i) - (log p_j - s_j))^2`` with
  ``w^l_ij = exp(-(1 - <pbar_i, pbar_j>)^2 / t_c^2) * [1 + exp(-(p_i^2 + p_j^2) / t_b^2)]``.

The input image is **linear RGB**. The intensity ``p`` is the channel mean, clamped to at least
``dark_eps`` before the log; the chromaticity ``pbar`` is the unit-norm RGB vector (channels
clamped to ``dark_eps`` so black pixels have a defined, neutral chromaticity). With the paper's
``t_c = 1e-4`` the chromaticity factor is nearly binary: it is ``>= 0.37`` only for pairs whose
colours differ by less than about 0.8 degrees (``1 - cos < 1e-4``) and vanishes otherwise, so
``S_l`` mostly ties pixels of identical chromaticity.

* ``S_s = sum_ij (s_i - s_j)^2`` over the same pairs (weight 1; pairs leaving the mask dropped).
  Not one of the paper's priors: where ``S_l`` cuts a pair (a chromaticity edge), the other
  terms decide the shading's offset across the edge only weakly, and an early-stopped solver
  keeps it from wherever it started (see :func:`smoothness_term`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchiid.core.check import check_finite, check_image, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.stencil import Stencil, half_offsets, shift_slices

__all__ = [
    "shading_stencil",
    "pair_mask",
    "midlevel_term",
    "smoothness_term",
    "retinex_weights",
    "edge_confidence",
    "retinex_term",
    "intensity",
    "pixel_confidence",
]


def _unit_chromaticity(image: torch.Tensor, dark_eps: float) -> torch.Tensor:
    """``I / ‖I‖`` per pixel (channels floored at ``dark_eps``), ``(B, 3, H, W)``.

    The norm as a sum of squares: ``Tensor.norm(dim=1)`` over the channel axis takes a slow
    strided path.
    """
    chrom = image.clamp_min(dark_eps)
    return chrom / chrom.square().sum(dim=1, keepdim=True).sqrt()


def shading_stencil(height: int, width: int, device: torch.device | str | None = None) -> Stencil:
    """The 3x3 half-offset stencil ``(0,1), (1,-1), (1,0), (1,1)`` shared by ``S_m`` and ``S_l``."""
    return Stencil.square(height, width, 3, device=device)


def pair_mask(
    stencil: Stencil, mask: torch.Tensor | None, dtype: torch.dtype
) -> torch.Tensor | None:
    """``(B, K, H, W)`` 0/1 factor: both pixels of a pair lie in ``mask`` (or ``None``)."""
    if mask is None:
        return None
    check_shape(mask, ("B", 1, stencil.height, stencil.width), "mask")
    m = mask.to(dtype)
    return m * stencil.neighbours(m)[:, 0]


def intensity(image: torch.Tensor, dark_eps: float = 1e-4) -> torch.Tensor:
    """Intensity ``p`` = channel mean of linear RGB, clamped to ``>= dark_eps``: ``(B,1,H,W)``."""
    return image.mean(dim=1, keepdim=True).clamp_min(dark_eps)


def midlevel_term(
    similarity: torch.Tensor,
    stencil: Stencil,
    t_m: float = 0.05,
    mask: torch.Tensor | None = None,
) -> StencilQuadratic:
    """The mid-level prior ``S_m`` (Eq. 4) from per-pair proposal similarities.

    Args:
        similarity: ``(B, K, H, W)`` values ``<g_i, g_{i + o_k}>`` for the stencil's offsets
            (``MidLevelFeatures.similarity(stencil)``); entries of pairs leaving the image are
            ignored.
        stencil: the 3x3 stencil (:func:`shading_stencil`).
        t_m: deviation (paper: 0.05).
        mask: optional ``(B, 1, H, W)`` bool; pairs leaving it get weight 0.

    Returns:
        ``StencilQuadratic`` with weights ``exp(-(1 - sim)^2 / t_m^2)``.

    Shape:
        unknowns ``(B, 1, H, W)``.
    """
    if t_m <= 0:
        raise ParameterError(f"t_m must be > 0, got {t_m}")
    check_shape(similarity, ("B", stencil.num_offsets, stencil.height, stencil.width), "similarity")
    sim = similarity * stencil.valid.to(similarity.device, similarity.dtype)
    check_finite(sim, "similarity")
    w = torch.exp(-((1 - sim) ** 2) / t_m**2)
    pm = pair_mask(stencil, mask, w.dtype)
    return StencilQuadratic(stencil, w if pm is None else w * pm)


def smoothness_term(
    stencil: Stencil,
    batch: int,
    mask: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float32,
) -> StencilQuadratic:
    """The plain shading smoothness ``S_s = Σ_ij (s_i − s_j)²`` over 3x3 neighbour pairs.

    Not one of the paper's priors. ``S_l`` ties the reflectance of neighbours of the same
    chromaticity and cuts every pair across a chromaticity edge (``t_c = 1e-4``); ``S_c`` and
    ``S_m`` tie patches and proposals, and the matting Laplacian's null space contains shading
    that jumps wherever its base image does. So across a chromaticity edge the energy decides
    only weakly whether the shading steps, and an early-stopped solve keeps whatever step its
    start left there (the documentation's Method page, "Additions to the energy").
    A small weight (``lambda_s``) pulls the shading towards continuity there and is negligible
    where ``S_l`` ties pixels (its weights are about 1 per pair, ``lambda_l`` = 2).

    Args:
        stencil: the 3x3 stencil (:func:`shading_stencil`).
        batch: number of images.
        mask: optional ``(B, 1, H, W)`` bool; pairs leaving it get weight 0.
        dtype: working dtype.

    Returns:
        ``StencilQuadratic`` with weight 1 on every pair inside the image (and mask).

    Shape:
        unknowns ``(B, 1, H, W)``.
    """
    if batch < 1:
        raise ParameterError(f"batch must be >= 1, got {batch}")
    valid = stencil.valid.to(device=stencil.device, dtype=dtype)
    w = valid.expand(batch, stencil.num_offsets, stencil.height, stencil.width).contiguous()
    pm = pair_mask(stencil, mask, dtype)
    return StencilQuadratic(stencil, w if pm is None else w * pm)


#: Largest value an image may reach and still count as low dynamic range (values in [0, 1]);
#: only such images can have pixels clipped at the ceiling.
_LDR_MAX = 1.0 + 1e-3


def pixel_confidence(
    image: torch.Tensor, dark_level: float = 0.002, clip_level: float = 0.99
) -> torch.Tensor:
    """How much each pixel's colour can be trusted, ``(B, 3, H, W) -> (B, 1, H, W)`` in [0, 1].

    Two kinds of pixel carry no information about the shading's variation:

    * **dark** ones: with every channel near 0 the sensor noise and the 8-bit quantisation
      dominate (a linear value of 0.002 is sRGB code 6.5, one code step there is a 30%
      change of intensity), so ``log p`` differences and chromaticities are noise. The
      confidence ramps from 0 at ``max_c I_c = dark_level`` to 1 at ``2 * dark_level``.
    * **clipped** ones: a channel at the ceiling of a low-dynamic-range image (every value
      ``<= 1``) lost the true intensity. The confidence ramps from 1 at
      ``max_c I_c = clip_level - 0.03`` to 0 at ``clip_level``. Images with values above 1
      (HDR input) have no ceiling and no clipped pixels.

    ``dark_level = 0`` or ``clip_level = 0`` switches that kind off.

    Shape:
        image ``(B, 3, H, W)`` linear RGB -> ``(B, 1, H, W)``.
    """
    if dark_level < 0 or clip_level < 0:
        raise ParameterError(
            f"dark_level and clip_level must be >= 0, got {dark_level} and {clip_level}"
        )
    peak = image.amax(dim=1, keepdim=True)
    conf = torch.ones_like(peak)
    if dark_level > 0:
        conf = conf * ((peak - dark_level) / dark_level).clamp(0, 1)
    if clip_level > 0:
        ldr = (image.flatten(1).amax(1) <= _LDR_MAX).to(image.dtype).view(-1, 1, 1, 1)
        clipped = 1 - ((clip_level - peak) / 0.03).clamp(0, 1)
        conf = conf * (1 - ldr * clipped)
    return conf


def edge_confidence(
    image: torch.Tensor,
    t_e: float,
    dark_eps: float = 1e-4,
    mask: torch.Tensor | None = None,
    t_d: float = 0.0,
    t_h: float = 0.0,
) -> torch.Tensor:
    """How far each pixel is from a material edge, ``(B, 3, H, W) -> (B, 1, H, W)`` in [0, 1].

    ``exp(-e_i^2)`` with ``e_i = max_j (1 - <pbar_i, pbar_j>) / t_e`` over the 8 neighbours
    ``j`` (inside ``mask``, if given): 1 inside a region of one chromaticity, about 0 on a
    pixel beside a colour edge (``t_e`` 0.015: a 10 degree change gives 0.36, 5 degrees 0.94).
    With ``t_d > 0`` a step of log-intensity also counts: ``e_i`` is the larger of that and
    ``max_j |log p_i - log p_j| / t_d``, so pixels beside a sharp brightness step (black text
    on white paper: ``t_d`` 0.5 marks steps of more than about 1.6x) are marked too. With
    ``t_h > 0`` so are thin strokes: ``e_i`` also takes the height of a dark or bright line at
    most 4 px wide through the pixel (a top-hat of ``log p``, :data:`STROKE_SIZE`) over ``t_h``,
    which marks printed lettering but not a shadow's or a crease's step. 0 leaves a kind out.

    Such a pixel often mixes the two materials, and a mixture of a bright and a dark colour
    has nearly the bright one's chromaticity at a fraction of its light: ``0.4 * cream +
    0.6 * dark green`` (linear ``(0.8, 0.75, 0.55)`` and ``(0.006, 0.018, 0.008)``) is 0.6
    degrees from cream's chromaticity at 2.4x less light. ``S_l`` then ties it to the cream
    beside it and asks the shading to take that intensity step, which moves a bright print's
    whole level into the shading (the documentation's Method page, "Additions to the
    energy"). :func:`retinex_term` with ``t_e > 0`` multiplies
    ``S_l``'s weights by ``min(e_i, e_j)``, so the shading's level across a colour edge is left
    to the other priors (``S_s``, ``S_m``, ``S_c``). A sharp brightness step of one colour is
    print as often as it is a shadow's or a crease's edge; ``t_d`` takes it for print. A thin
    stroke is rarely shading; ``t_h`` takes it for print (the ``print`` preset).
    """
    if min(t_e, t_d, t_h) < 0 or not max(t_e, t_d, t_h) > 0:
        raise ParameterError(
            f"t_e, t_d and t_h must be >= 0 and one > 0, got t_e={t_e}, t_d={t_d}, t_h={t_h}"
        )
    b, _, h, w = image.shape
    if mask is not None:
        check_shape(mask, ("B", 1, h, w), "mask")
        if mask.shape[0] not in (1, b):
            raise ShapeError(f"mask has batch {mask.shape[0]}; expected 1 or the image's batch {b}")
        mask = mask.to(torch.bool).expand(b, 1, h, w)  # nonzero is inside
    logp = intensity(image, dark_eps).log() if t_d > 0 or t_h > 0 else None
    e = torch.zeros(b, 1, h, w, dtype=image.dtype, device=image.device)
    if t_e > 0 or t_d > 0:
        # each pixel against its 8 neighbours, one pair at a time: the deviation of a pair is
        # symmetric, so the 4 half-offsets give it to both pixels (a neighbour outside the
        # mask counts for neither: d · [j inside] for i, d · [i inside] for j)
        chrom = _unit_chromaticity(image, dark_eps) if t_e > 0 else None
        inside = None if mask is None else mask.to(image.dtype)
        for dy, dx in half_offsets(3):
            ys_i, xs_i, ys_j, xs_j = shift_slices(dy, dx, h, w)
            at_i, at_j = (..., ys_i, xs_i), (..., ys_j, xs_j)
            if chrom is not None:
                d = (1 - (chrom[at_i] * chrom[at_j]).sum(1, keepdim=True)) / t_e
                if t_d > 0 and logp is not None:
                    d = torch.maximum(d, (logp[at_i] - logp[at_j]).abs() / t_d)
            elif logp is not None:
                d = (logp[at_i] - logp[at_j]).abs() / t_d
            for mine, theirs in ((at_i, at_j), (at_j, at_i)):
                seen = d if inside is None else d * inside[theirs]
                e[mine] = torch.maximum(e[mine], seen)
    if t_h > 0 and logp is not None:
        e = torch.maximum(e, _stroke_height(logp, mask) / t_h)
    return torch.exp(-(e**2))


#: Side (px, at the working resolution) of the square that :func:`_stroke_height` closes and
#: opens with: strokes up to 4 px wide count as print.
STROKE_SIZE = 5


def _stroke_height(logp: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """How far each pixel lies below (or above) its surroundings across a thin stroke.

    The larger of the black top-hat ``closing(l) - l`` and the white top-hat ``l - opening(l)``
    of the log-intensity ``l`` with a ``STROKE_SIZE`` square: a dark (bright) line narrower than
    the square has the height of its step, a step edge or a smooth ramp has 0. Pixels outside
    ``mask`` take no part (they are blacked out and would make every object's outline a stroke).
    """
    r = STROKE_SIZE // 2
    inside = None if mask is None else mask.to(torch.bool)

    def grow(x: torch.Tensor) -> torch.Tensor:  # dilation over the pixels inside
        if inside is not None:
            x = x.masked_fill(~inside, -math.inf)
        return F.max_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), STROKE_SIZE, 1)

    def shrink(x: torch.Tensor) -> torch.Tensor:  # erosion over the pixels inside
        return -grow(-x)

    black = shrink(grow(logp)) - logp
    white = logp - grow(shrink(logp))
    height = torch.maximum(black, white)
    if inside is not None:
        height = height.masked_fill(~inside, 0.0)
    # a stroke's anti-aliased rim stands less far from the paper than its core; it takes the
    # core's height, so that no pair ties the stroke to the paper through it
    return F.max_pool2d(F.pad(height, (1, 1, 1, 1), mode="replicate"), 3, 1)


def _retinex_pairs(
    image: torch.Tensor,
    stencil: Stencil,
    t_c: float,
    t_b: float,
    dark_eps: float,
    t_i: float,
    t_e: float,
    mask: torch.Tensor | None,
    t_d: float,
    t_h: float,
    confidence: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``S_l``'s pair weights ``w^l``, their colour factor ``f'`` and the trusted share of it.

    :func:`retinex_weights` and :func:`retinex_term` both weigh the pairs with this ``w^l``.
    Under a pixel ``confidence`` each pair mixes two asks: with ``c_ij = min(c_i, c_j)`` its
    own (colour factor ``f``: chromaticity, intensity, edge; its target difference) and with
    ``1 - c_ij`` smooth shading (factor 1, target 0). ``f' = c_ij f + 1 - c_ij``, the trusted
    share is ``c_ij f`` (both ``f`` without a confidence), and the pair's target is its
    difference times their ratio (the weighted mean of the two targets).
    """
    if t_c <= 0 or t_b <= 0:
        raise ParameterError(f"t_c and t_b must be > 0, got t_c={t_c}, t_b={t_b}")
    if min(t_i, t_e, t_d, t_h) < 0:
        raise ParameterError(
            f"t_i, t_e, t_d and t_h must be >= 0 (0: off), got t_i={t_i}, t_e={t_e}, "
            f"t_d={t_d}, t_h={t_h}"
        )
    chrom = _unit_chromaticity(image, dark_eps)
    cos = (chrom.unsqueeze(2) * stencil.neighbours(chrom)).sum(1)  # (B, K, H, W)
    p = intensity(image, dark_eps)
    pj = stencil.neighbours(p)[:, 0]
    dark = 1 + torch.exp(-(p**2 + pj**2) / t_b**2)
    colour = torch.exp(-((1 - cos) ** 2) / t_c**2)
    if t_i > 0:
        dlog = p.log() - pj.log()
        colour = colour * torch.exp(-(dlog**2) / t_i**2)
    if t_e > 0 or t_d > 0 or t_h > 0:
        marks = edge_confidence(image, t_e, dark_eps, mask, t_d, t_h)
        colour = colour * pair_confidence(stencil, marks)
    trusted = colour
    if confidence is not None:
        c = pair_confidence(stencil, confidence).clamp(0, 1)
        trusted = c * colour
        colour = trusted + (1 - c)
    return colour * dark * stencil.valid.to(colour.device, colour.dtype), colour, trusted


def retinex_weights(
    image: torch.Tensor,
    stencil: Stencil,
    t_c: float = 1e-4,
    t_b: float = 0.05,
    dark_eps: float = 1e-4,
    confidence: torch.Tensor | None = None,
    t_i: float = 0.0,
    t_e: float = 0.0,
    mask: torch.Tensor | None = None,
    t_d: float = 0.0,
    t_h: float = 0.0,
) -> torch.Tensor:
    """Pair weights ``w^l`` of ``S_l`` (Eq. 5), ``(B, 3, H, W) -> (B, K, H, W)``.

    ``exp(-(1 - <pbar_i, pbar_j>)^2 / t_c^2) * [1 + exp(-(p_i^2 + p_j^2) / t_b^2)]`` on linear RGB.
    With ``t_i > 0`` the chromaticity factor is also multiplied by the intensity factor
    ``exp(-(log p_i - log p_j)^2 / t_i^2)``: two neighbours of the same chromaticity but very
    different brightness (dark print on a light ground of its hue) are no longer declared the
    same material; their shading is left to the other, non-local priors (``t_i = 0``: the
    paper's weights). With ``t_e``, ``t_d`` or ``t_h > 0`` it is also multiplied by
    ``min(e_i, e_j)`` (:func:`edge_confidence`, neighbours inside ``mask``; ``mask`` is used for
    these marks only, pairs leaving it keep their weight here and are dropped by
    :func:`retinex_term`): pixels beside a colour edge (or a sharp brightness step, or on a thin
    stroke) are not tied. With a pixel
    ``confidence`` (:func:`pixel_confidence`) and ``c_ij = min(c_i, c_j)``, the colour factor
    becomes ``c_ij * factor + (1 - c_ij)``: a pair without trustworthy colours (dark or
    clipped) is not cut apart by its noisy colour.
    """
    pairs = _retinex_pairs(image, stencil, t_c, t_b, dark_eps, t_i, t_e, mask, t_d, t_h, confidence)
    return pairs[0]


def pair_confidence(stencil: Stencil, confidence: torch.Tensor) -> torch.Tensor:
    """``min(c_i, c_j)`` for every stencil pair, ``(B, 1, H, W) -> (B, K, H, W)``."""
    check_shape(confidence, ("B", 1, stencil.height, stencil.width), "confidence")
    return torch.minimum(confidence, stencil.neighbours(confidence)[:, 0])


def retinex_term(
    image: torch.Tensor,
    stencil: Stencil,
    t_c: float = 1e-4,
    t_b: float = 0.05,
    dark_eps: float = 1e-4,
    mask: torch.Tensor | None = None,
    confidence: torch.Tensor | None = None,
    t_i: float = 0.0,
    t_e: float = 0.0,
    t_d: float = 0.0,
    t_h: float = 0.0,
) -> StencilQuadratic:
    """The local Retinex prior ``S_l`` (Eq. 5) on the log-shading.

    ``sum w^l_ij ((log p_i - s_i) - (log p_j - s_j))^2 = sum w^l_ij (s_i - s_j - c_ij)^2`` with
    the target differences ``c_ij = log p_i - log p_j``.

    Args:
        image: ``(B, 3, H, W)`` linear RGB, ``>= 0``.
        stencil: the 3x3 stencil (:func:`shading_stencil`).
        t_c: chromaticity deviation (paper: 1e-4, nearly binary, see the module notes).
        t_b: dark-pixel deviation (paper: 0.05).
        dark_eps: intensity/channel floor before logs and normalisation.
        mask: optional ``(B, 1, H, W)`` bool; pairs leaving it get weight 0.
        confidence: optional ``(B, 1, H, W)`` pixel confidence in [0, 1]
            (:func:`pixel_confidence`). With ``c_ij = min(c_i, c_j)`` each pair is the sum
            of two asks: ``c_ij`` times the pair's own (colour factor ``f``, target
            difference ``c``) and ``1 - c_ij`` times smooth shading (factor 1, target 0).
            Its weight is ``c_ij f + 1 - c_ij`` (:func:`retinex_weights`) and its target
            ``c * c_ij f / (c_ij f + 1 - c_ij)``, so where the image carries no information
            (dark or clipped pixels) the term asks for ``s_i = s_j`` instead of copying
            noise, and a pair whose colours differ (``f = 0``) asks for no step at all.
        t_i: intensity deviation (0: off, the paper's weights); see :func:`retinex_weights`.
        t_e: colour-edge deviation (0: off, the paper's weights): pairs touching a pixel
            beside a chromaticity edge are not tied (:func:`edge_confidence`).
        t_d: brightness-step deviation of the same marks (0: off).
        t_h: stroke-height deviation of the same marks (0: off; the ``print`` preset).

    Returns:
        ``StencilQuadratic`` with target differences of ``log p``.
    """
    check_image(image, "image", channels=3)
    if image.shape[-2:] != (stencil.height, stencil.width):
        raise ShapeError(
            f"image is {tuple(image.shape[-2:])} but the stencil is "
            f"{(stencil.height, stencil.width)}"
        )
    w, colour, trusted = _retinex_pairs(
        image, stencil, t_c, t_b, dark_eps, t_i, t_e, mask, t_d, t_h, confidence
    )
    logp = intensity(image, dark_eps).log()
    target = stencil.apply(logp)[:, 0]
    if confidence is not None:
        # the weighted mean of the pair's own target and smooth shading's 0: a pair its colour
        # cuts (f = 0) asks for no share of the intensity step
        target = target * trusted / colour.clamp_min(torch.finfo(colour.dtype).tiny)
    pm = pair_mask(stencil, mask, w.dtype)
    if pm is not None:
        w = w * pm
    return StencilQuadratic(stencil, w, target)
