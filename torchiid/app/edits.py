"""The page's edits, composed from :mod:`torchiid.edit` on a session's layers.

Every control of the page is a field of :class:`EditSettings`; :func:`apply_edits` applies
them in one fixed order to a :class:`~torchiid.app.session.Layers` at any resolution:

1. the base layers: the merged components of both stages (:func:`torchiid.edit.merge`) or
   Stage 2's ``R, S``;
2. illumination intensity (:func:`~torchiid.edit.illumination_intensity`, defined from both
   stages: it starts from the merged components, as ``torchiid edit`` does);
3. the selected object's reflectance: flattened (:func:`~torchiid.edit.remove_texture`),
   retextured (:func:`~torchiid.edit.replace_albedo`) and recoloured
   (:func:`~torchiid.edit.recolour`);
4. soften shadows (:func:`~torchiid.edit.soften_shadows`);
5. illumination colour (:func:`~torchiid.edit.illumination_colour`);

and the result is ``R' · S'``. The preview runs this on the preview layers (hundreds of
pixels a side: milliseconds per edit), the download on the full-resolution layers, with the
same relative sizes (blurs and fall-offs are fractions of the longer side, the texture's
tiles are scaled with the photo), so the download is the preview at full resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid import edit
from torchiid.app.session import Layers, Session
from torchiid.core.exceptions import ImageError
from torchiid.io import load_image

__all__ = ["EditSettings", "Edited", "apply_edits", "render"]


@dataclass(frozen=True)
class EditSettings:
    """The edit controls of the page (the defaults change nothing).

    Attributes:
        merge: edit the merged components of both stages (else Stage 2's ``R, S``).
        tint: the light's colour, ``#rrggbb`` (or anything :func:`torchiid.edit.parse_colour`
            reads).
        tint_strength: how much of the tint the light near the brightest regions takes (0-1).
        intensity: light added to indirectly lit regions (0: none).
        soften: shadows lifted (0 < soften <= 1) or deepened (soften < 0).
        hue: the selected object's hue rotation in degrees.
        chroma: the selected object's chroma factor (1: unchanged).
        flatten: the selected object's reflectance made one flat colour.
        texture: an image file whose colours become the selected object's reflectance.
        fit: how the texture covers the object: ``"tile"`` or ``"stretch"``.
        scale: the texture's tile size factor, relative to the photo at full resolution.
    """

    merge: bool = True
    tint: str = "#ff9933"
    tint_strength: float = 0.0
    intensity: float = 0.0
    soften: float = 0.0
    hue: float = 0.0
    chroma: float = 1.0
    flatten: bool = False
    texture: str | None = None
    fit: str = "tile"
    scale: float = 1.0

    @property
    def object_edits(self) -> bool:
        """Whether any edit of the selected object is asked for."""
        return self.flatten or self.texture is not None or self.hue != 0 or self.chroma != 1


@dataclass(frozen=True)
class Edited:
    """An edit's result, ``(1, C, h, w)`` linear: the photo and its two edited layers."""

    image: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor


def load_texture(path: str) -> torch.Tensor:
    """A new albedo image as ``(3, h, w)`` linear; its errors name the control it came from.

    Raises:
        ImageError: the file cannot be read, as ``"new albedo: <file>: <problem>"``.
    """
    try:
        return load_image(path, min_side=1, alpha="ignore").image
    except ImageError as exc:
        raise ImageError(f"new albedo: {exc}") from None


def texture_of(session: Session, path: str) -> torch.Tensor:
    """The texture file as ``(3, h, w)`` linear, loaded once per session."""
    key = ("texture", path)
    if key not in session.cache:
        session.cache[key] = load_texture(path)
    return session.cache[key]


def _merged(session: Session, layers: Layers) -> edit.Merged:
    """The merged components of ``layers``; those of the preview are computed once."""
    key = ("merged", layers.size)
    if layers is session.preview and key in session.cache:
        return session.cache[key]
    merged = edit.merge(layers.image, layers.reflectance, layers.shading, layers.sigma, layers.rho)
    if layers is session.preview:
        session.cache[key] = merged
    return merged


def _object_edits(
    session: Session,
    layers: Layers,
    refl: torch.Tensor,
    shading: torch.Tensor,
    selection: torch.Tensor,
    s: EditSettings,
) -> torch.Tensor:
    """The selected object's reflectance edits, on the selection's bounding box only.

    Each of them changes nothing outside the selection and reads only inside it (the
    texture's tiles start at the selection's bounding box), so working on that box gives
    the same reflectance as working on the whole photo, for a fraction of the pixels.
    """
    rows = torch.nonzero(selection[0, 0].any(1))[:, 0]
    cols = torch.nonzero(selection[0, 0].any(0))[:, 0]
    box = (..., slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    r, sh, m = refl[box], shading[box], selection[box]
    if s.flatten:
        _, r = edit.remove_texture(r, sh, m)
    if s.texture is not None:
        # the tiles keep their size relative to the photo at every resolution
        scale = s.scale * layers.size[1] / session.full.size[1]
        tex = texture_of(session, s.texture)
        _, r = edit.replace_albedo(r, sh, m, tex, fit=s.fit, scale=scale)
    if s.hue != 0 or s.chroma != 1:
        _, r = edit.recolour(r, sh, m, hue=s.hue, chroma=s.chroma)
    out = refl.clone()
    out[box] = r
    return out


def apply_edits(
    session: Session,
    layers: Layers,
    settings: EditSettings,
    selection: torch.Tensor | None = None,
) -> Edited:
    """Apply the page's edits to ``layers`` (the session's preview or full-resolution ones).

    Args:
        session: the photo's session (its caches: merged layers, textures).
        layers: the layers to edit.
        settings: the controls.
        selection: ``(1, 1, h, w)`` bool, the selected object at the layers' resolution;
            without it the object edits do nothing.

    Returns:
        :class:`Edited`.

    Raises:
        ParameterError: a control's value is out of range (a colour that cannot be read, a
            soften above 1, ...).
        ImageError: the texture file cannot be read.
    """
    s = settings
    merged = None
    if s.merge or s.intensity > 0:
        merged = _merged(session, layers)
    if s.merge:
        refl, shading = merged.reflectance, merged.shading
    else:
        refl, shading = layers.reflectance, layers.shading
    if s.intensity > 0:
        _, shading = edit.illumination_intensity(
            layers.image,
            layers.reflectance,
            layers.shading,
            layers.sigma,
            layers.rho,
            s.intensity,
            merged=merged,
        )
        refl = merged.reflectance
    if selection is not None and bool(selection.any()) and s.object_edits:
        refl = _object_edits(session, layers, refl, shading, selection, s)
    if s.soften != 0:
        _, shading = edit.soften_shadows(refl, shading, s.soften)
    if s.tint_strength > 0:
        _, shading = edit.illumination_colour(refl, shading, s.tint, s.tint_strength)
    image = refl * shading
    if layers.mask is not None:  # outside the photo's alpha mask nothing is decomposed
        image = torch.where(layers.mask, image, layers.image)
    return Edited(image, refl, shading)


def render(
    session: Session,
    settings: EditSettings,
    proposal: int | None = None,
    *,
    full: bool = False,
) -> Edited:
    """The edits on the session's preview layers, or with ``full`` at full resolution.

    Args:
        session: the photo's session.
        settings: the controls.
        proposal: the selected object's proposal (:class:`~torchiid.app.objects.Objects`),
            or ``None``.
        full: edit the full-resolution layers (for the download) instead of the preview.

    Returns:
        :class:`Edited` at that resolution.
    """
    layers = session.full if full else session.preview
    selection = None
    if proposal is not None and session.objects is not None:
        selection = session.objects.mask(proposal, layers.size)
    return apply_edits(session, layers, settings, selection)
