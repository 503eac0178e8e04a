"""torchiid.edit.common: the Gaussian blur of the residue filters and the checks of numbers."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError
from torchiid.edit import (
    illumination_colour,
    illumination_intensity,
    merge,
    recolour,
    replace_albedo,
    soften_shadows,
)
from torchiid.edit.common import FAST_SIGMA, gaussian
from torchiid.synthetic import mondrian


@pytest.mark.parametrize("sigma", [2.0, 8.0, 20.0, 45.0])
def test_a_wide_gaussian_runs_at_a_lower_resolution_and_matches_the_exact_one(sigma):
    x = mondrian(240, 320, seed=3).image.double()
    x = x + 0.1 * torch.rand(x.shape, generator=torch.Generator().manual_seed(0), dtype=x.dtype)
    k = 2 * math.ceil(3 * sigma) + 1
    exact = kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")
    fast = gaussian(x, sigma)
    span = float(x.max() - x.min())
    assert float((fast - exact).abs().max()) < 0.003 * span
    if sigma >= 2 * FAST_SIGMA:  # a constant stays exactly constant
        ones = torch.ones(1, 3, 50, 70, dtype=torch.float64)
        torch.testing.assert_close(gaussian(ones, sigma), ones, atol=1e-12, rtol=0)


def test_no_blur_at_zero_sigma():
    x = torch.rand(1, 3, 8, 9)
    assert gaussian(x, 0.0) is x


def _layers():
    r = mondrian(32, 40, seed=1).reflectance
    s = torch.rand(1, 1, 32, 40, generator=torch.Generator().manual_seed(0)) + 0.2
    return r, s, torch.ones(1, 1, 32, 40, dtype=torch.bool)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r, s, m: recolour(r, s, m, hue=float("nan")), "hue must be a finite number"),
        (lambda r, s, m: recolour(r, s, m, hue=float("inf")), "hue must be a finite number"),
        (lambda r, s, m: recolour(r, s, m, chroma=float("inf")), "chroma must be a finite"),
        (lambda r, s, m: soften_shadows(r, s, float("nan")), "amount must be a finite number"),
        (lambda r, s, m: soften_shadows(r, s, 0.5, feather=-3.0), "feather must be >= 0"),
        (lambda r, s, m: soften_shadows(r, s, 0.5, feather=1e5), "feather must be <= 40"),
        (lambda r, s, m: illumination_colour(r, s, "red", float("nan")), "strength must be a"),
        (lambda r, s, m: merge(r * s, r, s, s, r, blur=float("nan")), "blur must be a finite"),
        (lambda r, s, m: merge(r * s, r, s, s, r, blur=1e9), "blur must be <= 40"),
        (lambda r, s, m: merge(r * s, r, s, s, r, blur=-1.0), "blur must be >= 0"),
        (lambda r, s, m: illumination_intensity(r * s, r, s, s, r, -5.0), "strength must be >= 0"),
        (
            lambda r, s, m: replace_albedo(r, s, m, torch.rand(3, 8, 8), scale=21.0),
            "scale must be at most 20",
        ),
    ],
)
def test_edit_numbers_out_of_range_raise_parameter_errors(edit, message):
    with pytest.raises(ParameterError, match=message):
        edit(*_layers())


def test_a_texture_with_nan_is_refused():
    r, s, m = _layers()
    with pytest.raises(ImageError, match="texture contains 12 NaN"):
        replace_albedo(r, s, m, torch.full((3, 2, 2), float("nan")))
