import dataclasses

import pytest
import torch

from torchiid.baselines import BaselineResult, reflectance_is_image, shading_is_image
from torchiid.core.exceptions import ShapeError


def test_reflectance_is_image():
    img = torch.rand(2, 3, 5, 7, dtype=torch.float64)
    out = reflectance_is_image(img, mask=torch.zeros(2, 1, 5, 7, dtype=torch.bool))
    assert isinstance(out, BaselineResult)
    assert torch.equal(out.reflectance, img) and out.reflectance is not img
    assert torch.equal(out.shading, torch.ones(2, 1, 5, 7, dtype=torch.float64))


def test_shading_is_image():
    img = torch.rand(1, 3, 4, 4)
    out = shading_is_image(img)
    assert torch.equal(out.reflectance, torch.ones_like(img))
    assert torch.equal(out.shading, img.mean(dim=1, keepdim=True))


def test_results_are_frozen_and_checked():
    out = shading_is_image(torch.rand(1, 3, 4, 4))
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.shading = out.reflectance
    for fn in (reflectance_is_image, shading_is_image):
        with pytest.raises(ShapeError):
            fn(torch.rand(3, 4, 4))
