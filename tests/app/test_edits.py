"""The page's edits composed on a session's layers, at the preview and at full resolution."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("gradio")

from torchiid.app.edits import EditSettings, render  # noqa: E402
from torchiid.core.exceptions import ParameterError  # noqa: E402


def _close(a: torch.Tensor, b: torch.Tensor, atol: float = 1e-4) -> bool:
    return bool(torch.allclose(a, b, atol=atol, rtol=1e-3))


@pytest.mark.parametrize("merge", [True, False])
def test_the_default_controls_change_nothing(chelsea_session, merge):
    s = chelsea_session
    edited = render(s, EditSettings(merge=merge))
    assert _close(edited.image, s.preview.image)
    full = render(s, EditSettings(merge=merge), full=True)
    assert _close(full.image, s.full.image)


def test_each_light_edit_moves_the_photo_the_way_it_says(chelsea_session):
    s = chelsea_session
    photo = s.preview.image
    lum = photo.mean(1, keepdim=True)
    dark = lum < lum.quantile(0.3)
    lighter = render(s, EditSettings(soften=0.8)).image.mean(1, keepdim=True)
    darker = render(s, EditSettings(soften=-0.8)).image.mean(1, keepdim=True)
    assert float(lighter[dark].mean()) > 1.5 * float(lum[dark].mean())
    assert float(darker[dark].mean()) < float(lum[dark].mean())
    lifted = render(s, EditSettings(intensity=1.0)).image
    assert float(lifted.mean()) > float(photo.mean())
    red = render(s, EditSettings(tint="#ff0000", tint_strength=1.0)).image
    ratio = lambda x: float(x[:, 0].sum() / x[:, 1].sum())  # noqa: E731
    assert ratio(red) > 1.05 * ratio(photo)


def test_object_edits_change_the_selected_object_only(chelsea_session, photos):
    s = chelsea_session
    p = s.objects.under(0.5, 0.5)[0]
    inside = s.objects.mask(p, s.preview.size)
    outside = ~inside
    plain = render(s, EditSettings())
    for settings in (
        EditSettings(hue=120),
        EditSettings(chroma=0),
        EditSettings(flatten=True),
        EditSettings(texture=str(photos["texture"]), fit="stretch"),
    ):
        edited = render(s, settings, p)
        changed = (edited.image - plain.image).abs().amax(1, keepdim=True) > 1e-3
        assert bool(changed[inside].any()), settings
        assert not bool(changed[outside].any()), settings
        # without a selection they do nothing
        assert _close(render(s, settings).image, plain.image)
    flat = render(s, EditSettings(flatten=True), p).reflectance
    colours = flat.permute(0, 2, 3, 1)[inside[:, 0]]
    assert float((colours - colours[0]).abs().max()) < 1e-6
    grey = render(s, EditSettings(chroma=0), p).reflectance
    assert float((grey[:, 0] - grey[:, 1])[inside[:, 0]].abs().max()) < 0.02


def test_the_full_resolution_edit_is_the_preview_at_full_resolution(photos):
    from torchiid.app.session import open_photo
    from torchiid.params import Parameters

    s = open_photo(photos["coffee"], Parameters().replace(iterations=1, max_side=150))
    assert s.preview.size == (100, 150) and s.full.size == (400, 600)
    p = s.objects.under(0.42, 0.38)[0]
    plain = F.interpolate(s.full.image, size=(100, 150), mode="area")
    texture = str(photos["texture"])
    for settings in (
        EditSettings(soften=0.5, intensity=0.3, hue=90, tint="#3366ff", tint_strength=0.6),
        EditSettings(texture=texture, scale=2.0),
    ):
        preview = render(s, settings, p).image
        full = render(s, settings, p, full=True).image
        assert full.shape == (1, 3, 400, 600)
        # the same edit: blurs, fall-offs, the selection and the texture's tiles scale with
        # the photo; what differs is the non-linear edits' response to the detail that the
        # preview averages away
        error = (F.interpolate(full, size=(100, 150), mode="area") - preview).abs().mean()
        effect = (preview - plain).abs().mean()
        assert float(error) < 0.25 * float(effect), settings


def test_bad_values_raise_the_library_errors(chelsea_session):
    with pytest.raises(ParameterError, match="cannot read the colour"):
        render(chelsea_session, EditSettings(tint="#12", tint_strength=0.5))
    with pytest.raises(ParameterError, match="amount must be <= 1"):
        render(chelsea_session, dataclasses.replace(EditSettings(), soften=2.0))
