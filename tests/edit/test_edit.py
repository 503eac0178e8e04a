"""torchiid.edit on synthetic scenes with known reflectance and shading."""

import pytest
import torch

from torchiid import edit
from torchiid.synthetic import mondrian


@pytest.fixture(scope="module")
def scene():
    return mondrian(48, 64, seed=3, dtype=torch.float64)


def _patch(h=48, w=64, y=(10, 30), x=(16, 44)):
    m = torch.zeros(1, 1, h, w, dtype=torch.bool)
    m[..., y[0] : y[1], x[0] : x[1]] = True
    return m


def _q8(x):
    return (x.clamp(0, 1) * 255).round()


def test_merge_of_exact_decomposition_is_identity(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    m = edit.merge(i, r, s, s, r)
    torch.testing.assert_close(m.c, torch.ones_like(m.c), atol=1e-9, rtol=0)
    torch.testing.assert_close(m.shading, s.expand(-1, 3, -1, -1), atol=1e-9, rtol=0)
    torch.testing.assert_close(m.reflectance, r, atol=1e-9, rtol=0)
    torch.testing.assert_close(m.sparse, i)


def test_merge_residue_is_gray_shading_disagreement(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = edit.gaussian(s, 3.0)
    m = edit.merge(i, r, s, sigma, i / sigma, blur=1.0)
    # both stages reconstruct I: C1 = S/σ, C2 = σ/S, gray and >= 1 after averaging
    torch.testing.assert_close(m.c1, (s / sigma).expand(-1, 3, -1, -1))
    assert float((m.c[:, 0] - m.c[:, 2]).abs().max()) < 1e-9
    assert float(m.c.min()) >= 1 - 1e-9
    torch.testing.assert_close(m.reflectance * m.shading, i)


def test_recolour_outside_unchanged_shading_kept(scene):
    r, s = scene.reflectance, scene.shading
    mask = _patch()
    out, new_r = edit.recolour(r, s, mask, hue=60, chroma=1.0)
    assert torch.equal(
        _q8(out)[~mask.expand(-1, 3, -1, -1)], _q8(r * s)[~mask.expand(-1, 3, -1, -1)]
    )
    inside = mask.expand(-1, 3, -1, -1)
    torch.testing.assert_close(out[inside], (new_r * s)[inside])
    assert float((new_r - r)[inside].abs().max()) > 0.05  # it did change
    lab0, lab1 = edit.linear_to_lab(r), edit.linear_to_lab(new_r)
    moved = ~((new_r == 0) | (new_r == 1)).any(1, keepdim=True) & mask  # not gamut-clipped
    assert float((lab0[:, :1] - lab1[:, :1])[moved].abs().max()) < 0.05  # L* within 0.05


def test_remove_texture_gives_flat_albedo_times_true_shading(scene):
    s = scene.shading
    mask = _patch()
    base = torch.tensor([0.6, 0.3, 0.2], dtype=torch.float64).view(1, 3, 1, 1)
    yy, xx = torch.meshgrid(torch.arange(48), torch.arange(64), indexing="ij")
    checker = (((yy // 3) + (xx // 3)) % 2).to(torch.float64) * 2 - 1  # +-1
    r = scene.reflectance.clone()
    r = torch.where(mask, base * (1 + 0.3 * checker), r)
    out, _ = edit.remove_texture(r, s, mask)
    flat = r[mask.expand(-1, 3, -1, -1)].view(3, -1).mean(1).view(1, 3, 1, 1)
    assert float((flat - base).abs().max()) < 0.01  # the checker averages out
    inside = mask.expand(-1, 3, -1, -1)
    err = (out - base * s)[inside].abs().max()
    assert float(err) < 0.01  # flat albedo x true shading within 0.01 (linear)
    assert torch.equal(out[~inside], (r * s)[~inside])


@pytest.mark.parametrize("fit", ["tile", "stretch"])
def test_replace_albedo_reproduces_texture_times_shading(scene, fit):
    r, s = scene.reflectance, scene.shading
    mask = _patch()
    tex = torch.rand(3, 7, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    out, new_r = edit.replace_albedo(r, s, mask, tex, fit=fit)
    region = new_r[..., 10:30, 16:44]
    if fit == "tile":
        want = tex.repeat(1, 3, 6)[None, :, :20, :28]
        torch.testing.assert_close(region, want)
    torch.testing.assert_close(out, new_r * s, atol=1e-12, rtol=0)
    assert torch.equal(new_r[..., :10, :], r[..., :10, :])


def test_illumination_colour_far_pixels_unchanged(scene):
    r, s = scene.reflectance, scene.shading
    out, new_s = edit.illumination_colour(r, s, "red", 1.0, percentile=0.95, radius=0.2)
    w = edit.light_weights(s, 0.95, 0.2)
    far = (w == 0).expand(-1, 3, -1, -1)
    assert int(far.sum()) > 100
    torch.testing.assert_close(out[far], scene.image[far], atol=1e-12, rtol=0)
    near = (w == 1)[:, 0]
    assert float((new_s[:, 0] - new_s[:, 1])[near].mean()) > 0.05  # reddish light there
    out_g, new_sg = edit.illumination_colour(r, s, "0,255,0", 1.0, radius=0.2)
    assert float((new_sg[:, 1] - new_sg[:, 0])[near].mean()) > 0.05


def test_illumination_intensity_raises_dark_keeps_bright(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = edit.gaussian(s, 4.0) * 0.9 + 0.1 * s.mean()  # a smoother Stage 1 shading
    rho = (i / sigma).clamp(0, 1)
    for combine in edit.COMBINE:
        out, new_s = edit.illumination_intensity(i, r, s, sigma, rho, 0.5, combine=combine)
        y = s[:, 0]
        dark = y <= torch.quantile(y, 0.1)
        bright = y >= torch.quantile(y, 0.99)
        gain = new_s.mean(1) / edit.merge(i, r, s, sigma, rho).shading.mean(1)
        assert float(gain[dark].mean()) > 1.05, combine
        rel = ((out - i).abs() / i).permute(1, 0, 2, 3)[:, bright]
        assert float(rel.max()) < 0.02, combine  # brightest 1%: within 2%
        assert float((out / i).min()) > 0.97


def test_soften_shadows(scene):
    r, s = scene.reflectance, scene.shading
    _, s0 = edit.soften_shadows(r, s, 0.0)
    torch.testing.assert_close(s0, s)
    _, s1 = edit.soften_shadows(r, s, 0.5)
    span = lambda x: float(x.log().amax() - x.log().amin())  # noqa: E731
    assert span(s1) < 0.6 * span(s)
    _, s2 = edit.soften_shadows(r, s, -0.5)
    assert span(s2) > 1.4 * span(s)
    mask = _patch()
    out, s3 = edit.soften_shadows(r, s, 0.5, mask=mask)
    assert torch.equal(s3[~mask], s[~mask])
    torch.testing.assert_close(out, r * s3)


def test_modules_and_parse_colour(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    m = edit.Merge()(i, r, s, s, r)
    torch.testing.assert_close(m.reflectance, r)
    out, _ = edit.SoftenShadows(0.0)(r, s)
    torch.testing.assert_close(out, i)
    assert edit.parse_colour("#ff8000") == (1.0, 128 / 255, 0.0)
    assert edit.parse_colour("0.5,0.5,1") == (0.5, 0.5, 1.0)
    with pytest.raises(edit.ParameterError):
        edit.parse_colour("purple-ish")


@pytest.mark.parametrize("sigma", [8.0, 20.0, 45.0])
def test_a_wide_gaussian_runs_at_a_lower_resolution_and_matches_the_exact_one(sigma):
    import math

    import kornia

    x = mondrian(240, 320, seed=3).image.double()
    x = x + 0.1 * torch.rand(x.shape, generator=torch.Generator().manual_seed(0), dtype=x.dtype)
    k = 2 * math.ceil(3 * sigma) + 1
    exact = kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")
    fast = edit.gaussian(x, sigma)
    span = float(x.max() - x.min())
    assert float((fast - exact).abs().max()) < 0.003 * span
    if sigma >= 2 * edit.FAST_SIGMA:  # a constant stays exactly constant
        ones = torch.ones(1, 3, 50, 70, dtype=torch.float64)
        torch.testing.assert_close(edit.gaussian(ones, sigma), ones, atol=1e-12, rtol=0)
