import numpy as np
import pytest
import torch

from torchiid.baselines import ColorRetinex, RetinexResult, color_retinex
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval import mit_lmse
from torchiid.synthetic import mondrian


def _image(seed=0, h=12, w=14, b=1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, h, w, generator=g, dtype=torch.float64) * 0.8 + 0.1


def test_product_shapes_and_mask_outside():
    img = _image(b=2).float()
    mask = torch.ones(2, 1, 12, 14, dtype=torch.bool)
    mask[1, :, :, :4] = False
    out = color_retinex(img, mask)
    assert isinstance(out, RetinexResult)
    r, s = out.reflectance, out.shading
    assert r.shape == (2, 3, 12, 14) and s.shape == (2, 1, 12, 14)
    assert r.dtype == torch.float32 and s.dtype == torch.float32
    assert bool((s[1, :, :, :4] == 1).all()) and torch.equal(r[1, :, :, :4], img[1, :, :, :4])
    # reflectance normalisation: gray max inside the mask is 1
    gray_max = r.mean(1, keepdim=True).masked_fill(~mask, 0).amax(dim=(1, 2, 3))
    assert torch.allclose(gray_max, torch.ones(2), atol=1e-5)
    # batch == one by one
    one = color_retinex(img[1:], mask[1:])
    r1, s1 = one.reflectance, one.shading
    assert torch.allclose(r1, r[1:], atol=1e-5) and torch.allclose(s1, s[1:], atol=1e-5)
    mod = ColorRetinex()(img, mask)
    assert torch.equal(mod.reflectance, r) and torch.equal(mod.shading, s)


def test_extreme_thresholds():
    img = _image()
    # every difference is reflectance: shading constant, gray reflectance ∝ gray image
    s = color_retinex(img, threshold_gray=0.0, threshold_color=0.0).shading
    assert torch.allclose(s, s.mean().expand_as(s), rtol=1e-6)
    # no difference is reflectance: gray reflectance constant, shading ∝ gray image
    out = color_retinex(img, threshold_gray=1e9, threshold_color=1e9)
    r, s = out.reflectance, out.shading
    gray_r = r.mean(1)
    assert torch.allclose(gray_r, torch.ones_like(gray_r), rtol=1e-6)
    assert torch.allclose(s, img.mean(1, keepdim=True), rtol=1e-6)


def _reference_log_reflectance(img, mask, tg, tc, eps):
    """Dense float64 least squares: independent of the torch code."""
    x = np.maximum(img, eps)
    log_i = np.log(x)
    log_g = np.log(np.maximum(img.mean(0), eps))
    h, w = mask.shape
    idx = np.arange(h * w).reshape(h, w)
    rows, targets = [], []
    for axis in (0, 1):
        d = np.diff(log_i, axis=axis + 1)
        gray = d.mean(0)
        chroma = np.sqrt(((d - gray) ** 2).sum(0))
        keep = (chroma > tc) | (np.abs(gray) > tg)
        dg = np.diff(log_g, axis=axis)
        a = idx[:-1, :] if axis == 0 else idx[:, :-1]
        b = idx[1:, :] if axis == 0 else idx[:, 1:]
        ma = mask[:-1, :] & mask[1:, :] if axis == 0 else mask[:, :-1] & mask[:, 1:]
        for (i, j), ok in np.ndenumerate(ma):
            if ok:
                row = np.zeros(h * w)
                row[b[i, j]], row[a[i, j]] = 1.0, -1.0
                rows.append(row)
                targets.append(dg[i, j] if keep[i, j] else 0.0)
    sol = np.linalg.lstsq(np.array(rows), np.array(targets), rcond=None)[0]
    return sol.reshape(h, w)


def test_poisson_solution_matches_dense_least_squares():
    img = _image(seed=4, h=8, w=9)[0]
    img[:, :, 5:] *= 0.3  # a reflectance edge
    img[0, 2:6, 2:4] *= 2.0  # a chromatic patch
    mask = np.ones((8, 9), dtype=bool)
    mask[0:3, 0:2] = False
    mask[6:, 7:] = False
    tg, tc, eps = 0.075, 0.3, 3 / 257
    r = color_retinex(img[None], torch.from_numpy(mask), tg, tc).reflectance
    ours = torch.log(r[0].mean(0)).numpy()
    ref = _reference_log_reflectance(img.numpy(), mask, tg, tc, eps)
    diff = (ours - ref)[mask]
    np.testing.assert_allclose(diff - diff.mean(), 0.0, atol=1e-6)


def test_gray_threshold_semantics():
    img = torch.full((1, 3, 6, 8), 0.5, dtype=torch.float64)
    img[..., :, 4:] *= np.exp(0.1)  # log step 0.1 > 0.075: reflectance
    s = color_retinex(img).shading
    assert torch.allclose(s, s.mean().expand_as(s), rtol=1e-6)
    img = torch.full((1, 3, 6, 8), 0.5, dtype=torch.float64)
    img[..., :, 4:] *= np.exp(0.05)  # log step 0.05 < 0.075: shading
    r = color_retinex(img).reflectance
    assert torch.allclose(r.mean(1), torch.ones(1, 6, 8, dtype=torch.float64), rtol=1e-6)


def test_mondrian_better_than_trivial_baseline():
    syn = mondrian(48, 48, patches=8, seed=1)
    out = color_retinex(syn.image)
    ours = mit_lmse(syn.reflectance, syn.shading, out.reflectance, out.shading).item()
    ones = torch.ones_like(syn.shading)
    r_is_i = mit_lmse(syn.reflectance, syn.shading, syn.image, ones).item()
    assert ours < 0.5 * r_is_i


def test_retinex_errors():
    with pytest.raises(ShapeError):
        color_retinex(torch.rand(1, 1, 8, 8))
    with pytest.raises(ShapeError):
        color_retinex(torch.rand(1, 3, 8, 8), torch.ones(1, 1, 8, 9))
    with pytest.raises(ParameterError):
        color_retinex(torch.rand(1, 3, 8, 8), threshold_gray=-1)
