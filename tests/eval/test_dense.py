import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from torchiid.core.exceptions import ShapeError
from torchiid.eval import dssim, scale_to_match, si_mse, ssim


def test_si_mse_by_hand_and_invariance():
    gt = torch.tensor([1.0, 2.0]).view(1, 1, 1, 2)
    est = torch.ones_like(gt)  # alpha = 3/2, errors 0.25 + 0.25 over 2 pixels
    assert si_mse(gt, est).item() == pytest.approx(0.25)
    g = torch.rand(2, 3, 12, 12, generator=torch.Generator().manual_seed(0)) + 0.1
    e = g * torch.tensor([2.0, 0.5, 7.0]).view(1, 3, 1, 1)  # per-channel scale
    assert torch.allclose(si_mse(g, e), torch.zeros(2), atol=1e-12)
    noisy = g + 0.05 * torch.rand(2, 3, 12, 12)
    assert torch.allclose(si_mse(g, 3.0 * noisy), si_mse(g, noisy), rtol=1e-5)


def test_si_mse_mask_ignores_outside():
    g = torch.rand(1, 3, 8, 8) + 0.1
    e = g.clone()
    e[..., :, 4:] = 5.0
    mask = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    mask[..., :, :4] = True
    assert si_mse(g, e, mask).item() == pytest.approx(0.0, abs=1e-12)
    assert si_mse(g, e).item() > 0
    assert torch.allclose(scale_to_match(g, 2 * g), g, atol=1e-6)


def test_ssim_matches_skimage():
    rng = np.random.default_rng(1)
    a = rng.random((3, 32, 40))
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    ref = structural_similarity(
        a,
        b,
        channel_axis=0,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
    )
    out = ssim(torch.from_numpy(a)[None], torch.from_numpy(b)[None]).item()
    assert out == pytest.approx(ref, rel=1e-9)


def test_dssim_properties():
    g = torch.rand(2, 3, 24, 24, generator=torch.Generator().manual_seed(2))
    assert torch.allclose(dssim(g, g), torch.zeros(2), atol=1e-12)
    d = dssim(g, torch.rand(2, 3, 24, 24))
    assert bool(((d > 0) & (d <= 1)).all())
    assert dssim(g, 0.5 * g).min() > 0
    assert torch.allclose(dssim(g, 0.5 * g, scale_invariant=True), torch.zeros(2), atol=1e-6)


def test_dense_errors():
    with pytest.raises(ShapeError):
        si_mse(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))
    with pytest.raises(ShapeError):
        dssim(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8))  # smaller than the window
