"""torchiid.edit.common: the Gaussian blur of the residue filters."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

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
