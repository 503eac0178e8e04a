"""Selecting an object by a click: the proposals under it, nested, and their masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("gradio")

from torchiid.app.objects import MIN_FRACTION, Objects, highlight  # noqa: E402


def test_the_objects_under_a_click_are_nested_regions_that_hold_it(chelsea_session):
    objects = chelsea_session.objects
    h, w = objects.size
    for u, v in ((0.5, 0.5), (0.1, 0.9), (0.95, 0.05)):
        found = objects.under(u, v)
        assert found, (u, v)
        areas = [float(objects.areas[p]) for p in found]
        assert areas == sorted(areas) and len(set(areas)) == len(areas)
        assert areas[0] >= MIN_FRACTION * h * w
        y, x = min(int(v * h), h - 1), min(int(u * w), w - 1)
        for p in found:
            mask = objects.mask(p)
            assert mask.shape == (1, 1, h, w) and bool(mask[0, 0, y, x])
            assert int(mask.sum()) == round(float(objects.areas[p]))


def test_a_mask_at_another_resolution_covers_the_same_region(chelsea_session):
    objects = chelsea_session.objects
    p = objects.under(0.5, 0.5)[0]
    small = objects.mask(p).float().mean()
    big = objects.mask(p, (600, 800))
    assert big.shape == (1, 1, 600, 800) and big.dtype == torch.bool
    assert abs(float(big.float().mean()) - float(small)) < 0.02


def test_proposals_are_computed_when_stage_0_had_none(chelsea_session):
    image = chelsea_session.preview.image
    objects = Objects.from_image(image)
    assert objects.size == (150, 200)
    assert objects.under(0.5, 0.5)
    assert Objects.from_features(None) is None


def test_highlight_darkens_only_outside_the_mask():
    rgb = np.full((4, 6, 3), 90, np.uint8)
    mask = torch.zeros(1, 1, 4, 6, dtype=torch.bool)
    mask[..., 1:3, 2:5] = True
    out = highlight(rgb, mask)
    assert (out[1:3, 2:5] == 90).all() and (out[0] == 30).all()
    assert (rgb == 90).all()  # the input is left as it was
