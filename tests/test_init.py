"""``decompose(..., init=(R0, S0))``: a warm start from a given decomposition."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.synthetic import mondrian

# solves run to tolerance, so the answer does not depend on the starting point
CONVERGED = Parameters().replace(
    patch_size=8,
    patch_stride=4,
    iterations=1,
    cg_tol=1e-10,
    cg_max_iter=1000,
    warm_cg_max_iter=0,
    theta=2.5,  # the converged preset's splitting penalty: the same minimum, sooner
    bregman_iter=150,
    bregman_tol=1e-6,
    bregman_cg_iter=5,
    bregman_cg_tol=1e-10,
)


def test_warm_start_converges_to_the_cold_start():
    m = mondrian(16, 16, dtype=torch.float64)
    cold = decompose(m.image, CONVERGED)
    # a poor "network" guess: the true layers at another scale, blurred shading
    s0 = torch.nn.functional.avg_pool2d(m.shading, 3, 1, 1, count_include_pad=False) * 3.0
    warm = decompose(m.image, CONVERGED, init=(m.reflectance / 3.0, s0))
    assert cold.converged and warm.converged
    assert warm.solves[0].cap == CONVERGED.shading.cg_max_iter  # warm-started PCG (no cascade)
    torch.testing.assert_close(warm.reflectance, cold.reflectance, atol=1e-3, rtol=0)
    torch.testing.assert_close(warm.shading, cold.shading, atol=0, rtol=1e-3)
    torch.testing.assert_close(warm.reflectance * warm.shading, m.image.float().double())


def test_init_is_checked():
    img = mondrian(16, 16).image
    p = CONVERGED
    with pytest.raises(ShapeError):
        decompose(img, p, init=(img[:, :2], torch.ones(1, 1, 16, 16)))
    with pytest.raises(ShapeError):
        decompose(img, p, init=(img, torch.ones(1, 1, 8, 8)))
    with pytest.raises(ShapeError):
        decompose(img, p, init=img)
