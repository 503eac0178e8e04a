import pytest
import torch
import torch.nn.functional as F

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.params import Parameters
from torchiid.priors.texture import (
    EDGE_RADIUS,
    REMOVAL_SIGMA,
    colour_texture_evidence,
    detexture,
    texture_confidence,
)
from torchiid.synthetic_texture import smooth_light, textured_plane

TEXTURE_T_X = Parameters.preset("texture").shading.t_x


@pytest.mark.parametrize("t_x", [0.05, TEXTURE_T_X])
def test_smooth_light_and_soft_shadows_keep_full_confidence(t_x):
    for light in ("gradient", "shadow"):
        s = smooth_light(light, 128, 128).float().expand(1, 3, 128, 128) * 0.6
        c = texture_confidence(s, t_x)
        assert c.shape == (1, 1, 128, 128) and c.dtype == torch.float32
        assert c.min().item() > 0.9, light


@pytest.mark.parametrize("texture", ["wood", "fabric", "fur"])
def test_dense_texture_gets_low_confidence(texture):
    s = textured_plane(texture, "shadow", 128, 128)
    c = texture_confidence(s.image, 0.05)
    assert c.median().item() < 0.5, texture


@pytest.mark.parametrize("t_x", [0.05, TEXTURE_T_X])
def test_creases_and_sparse_print_keep_confidence(t_x):
    # two faces of a box meeting at a crease: a sharp step of the light, no texture
    light = torch.ones(1, 1, 64, 64)
    light[..., 32:] = 0.3
    c = texture_confidence(light.expand(1, 3, 64, 64) * 0.7, t_x)
    assert c.min().item() > 0.9
    s = textured_plane("print", "gradient", 128, 128)
    assert texture_confidence(s.image, t_x).median().item() > 0.9


def test_the_mask_rim_is_not_texture():
    # a smooth object on black: the step to the outside must not count inside the mask
    s = smooth_light("gradient", 96, 96).float().expand(1, 3, 96, 96) * 0.5
    mask = torch.zeros(1, 1, 96, 96, dtype=torch.bool)
    mask[..., 20:80, 15:85] = True
    inside = texture_confidence(s * mask, 0.05, mask)[mask]
    assert inside.min().item() > 0.9
    ignored = texture_confidence(s * mask, 0.05)[mask]
    assert ignored.min().item() < 0.1  # without the mask the rim looks like a sharp step


def test_bad_deviation_fails_clearly():
    with pytest.raises(ParameterError, match="t_x and window must be > 0"):
        texture_confidence(torch.rand(1, 3, 16, 16), 0.0)
    with pytest.raises(ParameterError, match="parameter t_x must be >= 0"):
        Parameters().replace(t_x=-1.0)


def test_the_parameter_default_is_the_prior_s_removal_scale():
    # the parameters keep their own literal so that they import without torch
    assert Parameters().shading.t_x_sigma == REMOVAL_SIGMA


def test_t_x_and_t_xc_by_preset_and_in_the_shading_group():
    assert (Parameters().shading.t_x, Parameters().shading.t_xc) == (0.02, 0.02)
    assert all(Parameters.preset(p).shading.t_x == 0.0 for p in ("paper", "print", "converged"))
    texture = Parameters.preset("texture").shading
    assert (texture.t_x, texture.t_xc) == (0.02, 0.0)
    assert Parameters().replace(t_x=0.05).alternation(3)[0].t_x == 0.05
    assert Parameters().replace(t_xc=0.05).alternation(3)[0].t_xc == 0.05
    with pytest.raises(ParameterError, match="parameter t_xc must be >= 0"):
        Parameters().replace(t_xc=-0.1)


@pytest.mark.parametrize("texture", ["tiles", "wood", "fur"])
def test_stage1_shading_keeps_less_texture_with_t_x(texture):
    from torchiid.eval import texture_in_shading
    from torchiid.model import decompose

    s = textured_plane(texture, "gradient", 96, 96)
    p = Parameters().replace(
        iterations=2, use_sc=False, use_sm=False, use_rm=False, use_rg=False, t_xc=0.0
    )
    measured = {}
    for t_x in (0.0, 0.05, TEXTURE_T_X):
        out = decompose(s.image, p.replace(t_x=t_x))
        measured[t_x] = texture_in_shading(out.sigma, s.image, s.shading).item()
    assert measured[0.05] < 0.5 * measured[0.0], measured
    # the preset's detection and coarser removal leave at most a sixth of the texture
    assert measured[TEXTURE_T_X] < min(0.6 * measured[0.05], measured[0.0] / 6), measured


def test_detexture_removes_dense_texture_and_keeps_light_and_colour():
    s = textured_plane("wood", "shadow", 128, 128, dtype=torch.float64)
    out = detexture(s.image, 0.05)
    chroma = lambda x: x / x.sum(1, keepdim=True)  # noqa: E731
    assert torch.allclose(chroma(out), chroma(s.image), atol=1e-9)
    from torchiid.eval import texture_in_shading

    # as a "shading", the detextured image carries far less of the texture than the image,
    # and the light's soft shadow is still in it
    assert texture_in_shading(out, s.image, s.shading).item() < 0.4
    ratio = out.mean(1, keepdim=True) / s.image.mean(1, keepdim=True)
    assert 0.5 < ratio.min().item() and ratio.max().item() < 2.0
    smooth = smooth_light("gradient", 64, 64).expand(1, 3, 64, 64) * 0.5
    assert torch.allclose(detexture(smooth, 0.05, sigma=3.0), smooth, rtol=1e-6)


def test_coarse_grain_leaves_the_targets_of_s_l():
    # wood's rings (period about 9 px at 256 px) are coarser than the 1-px detection; the
    # texture preset marks their fine part and takes them out with the coarser removal fit,
    # where 1.0.0's t_x 0.05 with a 3-px fit left more than half of them
    from torchiid.eval import texture_in_shading

    s = textured_plane("wood", "gradient", 256, 256, dtype=torch.float64)
    assert texture_confidence(s.image, TEXTURE_T_X).median().item() < 0.1
    left = texture_in_shading(detexture(s.image, TEXTURE_T_X), s.image, s.shading).item()
    before = texture_in_shading(detexture(s.image, 0.05, sigma=3.0), s.image, s.shading).item()
    assert left < 0.2 < 0.5 < before, (left, before)
    # the coarser fit alone, at the same detection, leaves more
    finer = texture_in_shading(
        detexture(s.image, TEXTURE_T_X, sigma=3.0), s.image, s.shading
    ).item()
    assert left < 0.75 * finer, (left, finer)


def test_detexture_leaves_smooth_light_untouched_at_the_preset():
    smooth = smooth_light("gradient", 96, 96).expand(1, 3, 96, 96) * 0.5
    assert torch.allclose(detexture(smooth, TEXTURE_T_X), smooth, rtol=1e-5)
    # a soft shadow (3 px blur at 96 px) bends the light within a few pixels: its edge keeps
    # most of its confidence, so the targets move by a few percent at most
    shadow = smooth_light("shadow", 96, 96).expand(1, 3, 96, 96) * 0.5
    change = (detexture(shadow, TEXTURE_T_X) / shadow - 1).abs().max().item()
    assert change < 0.05, change


def _relief(size: int = 128, seed: int = 0) -> torch.Tensor:
    """A green surface of fine bumps under a light from the upper left (Lambert, one albedo)."""
    g = torch.Generator().manual_seed(seed)
    h = torch.randn(1, 1, size, size, generator=g, dtype=torch.float64)
    k = torch.exp(-(torch.arange(-6, 7, dtype=torch.float64) ** 2) / (2 * 1.5**2))
    k = k / k.sum()
    h = F.conv2d(F.pad(h, (6, 6, 6, 6), mode="circular"), (k[:, None] * k[None, :])[None, None])
    h = 6 * h / h.std()
    gy, gx = torch.gradient(h[0, 0])
    n = torch.stack([-gx, -gy, torch.ones_like(gx)])
    n = n / n.norm(dim=0, keepdim=True)
    light = torch.tensor([-0.5, -0.5, 0.7], dtype=torch.float64)
    shade = (n * (light / light.norm())[:, None, None]).sum(0).clamp_min(0) + 0.05
    albedo = torch.tensor([0.2, 0.5, 0.15], dtype=torch.float64)[:, None, None]
    return (albedo * shade)[None]


def test_colour_evidence_finds_texture_that_changes_colour():
    # wood and fur darken towards red; the tiles' levels and grout keep their hue
    for texture in ("wood", "fur"):
        s = textured_plane(texture, "shadow", 128, 128, dtype=torch.float64)
        evidence = colour_texture_evidence(s.image, 0.02)
        assert evidence.shape == (1, 1, 128, 128) and evidence.dtype == torch.float32
        assert evidence.median().item() > 0.9, texture
    tiles = textured_plane("tiles", "gradient", 128, 128, dtype=torch.float64)
    assert colour_texture_evidence(tiles.image, 0.02).mean().item() < 0.02


def test_fine_relief_of_one_colour_keeps_its_shading_marks():
    image = _relief()
    # the relief is dense fine variation of lightness: the texture preset takes it for texture
    assert texture_confidence(image, 0.02).median().item() < 0.1
    # but its colour does not change, so the default's marks leave it to the shading
    assert colour_texture_evidence(image, 0.02).max().item() < 0.05
    assert texture_confidence(image, 0.02, t_xc=0.02).min().item() > 0.95


def test_channel_noise_is_not_colour_evidence():
    g = torch.Generator().manual_seed(1)
    flat = torch.full((1, 3, 96, 96), 0.3, dtype=torch.float64)
    noisy = flat * torch.exp(0.08 * torch.randn(1, 3, 96, 96, generator=g, dtype=torch.float64))
    assert colour_texture_evidence(noisy, 0.02).mean().item() < 0.05


def test_no_colour_evidence_beside_a_colour_edge():
    s = textured_plane("wood", "gradient", 128, 128, dtype=torch.float64)
    image = s.image.clone()
    image[..., :, 60:] = image[..., :, 60:].flip(1)  # a blue-ish half: a material edge at x = 60
    evidence = colour_texture_evidence(image, 0.02)
    assert evidence[..., :, 60 - EDGE_RADIUS : 60 + EDGE_RADIUS].max().item() == 0.0
    assert evidence[..., :, 20:40].median().item() > 0.9


def test_bad_colour_slope_fails_clearly():
    with pytest.raises(ParameterError, match="t_xc and window must be > 0"):
        colour_texture_evidence(torch.rand(1, 3, 16, 16), 0.0)
    with pytest.raises(ParameterError, match="t_xc must be >= 0"):
        texture_confidence(torch.rand(1, 3, 16, 16), 0.02, t_xc=-1.0)


def test_detexture_takes_a_confidence_made_beforehand():
    s = textured_plane("wood", "gradient", 64, 64, dtype=torch.float64)
    c = texture_confidence(s.image, 0.02, t_xc=0.02)
    assert torch.equal(detexture(s.image, 0.02, t_xc=0.02), detexture(s.image, 0.02, confidence=c))
    with pytest.raises(ShapeError, match="confidence"):
        detexture(s.image, 0.02, confidence=c[..., :32, :])


def test_the_default_takes_coloured_texture_out_of_the_shading_and_keeps_relief():
    from torchiid.eval import texture_in_shading
    from torchiid.model import decompose

    p = Parameters().replace(iterations=2, use_sc=False, use_sm=False, use_rm=False, use_rg=False)
    s = textured_plane("wood", "gradient", 96, 96)
    left = {
        t_x: texture_in_shading(decompose(s.image, p.replace(t_x=t_x)).sigma, s.image, s.shading)
        for t_x in (0.0, 0.02)
    }
    assert left[0.02].item() < 0.5 * left[0.0].item(), left
    # a relief of one colour: its shading keeps the bumps under the default, as without t_x
    image = _relief(96).float()
    sig = {t_x: decompose(image, p.replace(t_x=t_x)).sigma.log() for t_x in (0.0, 0.02)}
    assert torch.allclose(sig[0.02], sig[0.0], atol=1e-4)
    gone = decompose(image, p.replace(t_xc=0.0)).sigma.log()  # the texture preset's marks
    relief = (sig[0.0] - F.avg_pool2d(sig[0.0], 7, 1, 3)).std()
    assert (gone - F.avg_pool2d(gone, 7, 1, 3)).std() < 0.7 * relief


def test_the_marks_are_made_once_per_image_and_averaged_for_coarser_levels(monkeypatch):
    import torchiid.pipeline.alternation as alternation
    import torchiid.stages.shading as shading
    import torchiid.stages.shading_system as system
    from torchiid.model import decompose
    from torchiid.stages.config import ShadingProblem
    from torchiid.stages.shading import solve_shading

    sizes = []

    def spy(image, *args, **kwargs):
        sizes.append(tuple(image.shape[-2:]))
        return texture_confidence(image, *args, **kwargs)

    monkeypatch.setattr(alternation, "texture_confidence", spy)
    monkeypatch.setattr(shading, "texture_confidence", spy)
    image = textured_plane("wood", "gradient", 96, 128).image
    # decompose: once, at the working resolution, for the half-size run and the solves' levels
    out = decompose(image, Parameters())
    assert sizes == [(96, 128)] and "texture marks" in out.times
    # a solve called directly: once per image, kept in the cache for the next alternation
    sizes.clear()
    cache = system.ShadingSystemCache()
    for k in (1, 2):
        solve_shading(
            ShadingProblem(image), Parameters().alternation(k)[0], cache=cache, warn=False
        )
    assert sizes == [(96, 128)]
    # off: never made
    sizes.clear()
    decompose(image, Parameters().replace(t_x=0.0))
    assert sizes == []
    # a coarse level takes it area-averaged
    c = texture_confidence(image, 0.02, t_xc=0.02)
    coarse = system.coarse_problem(ShadingProblem(image, texture=c), 1.0, 0.5)
    assert torch.allclose(coarse.texture, F.avg_pool2d(c, 2))


def test_a_two_dimensional_mask_works_with_the_colour_marks():
    s = textured_plane("wood", "gradient", 40, 50)
    mask = torch.zeros(40, 50, dtype=torch.bool)
    mask[5:35, 5:45] = True
    c2 = texture_confidence(s.image, 0.02, mask, t_xc=0.02)
    c4 = texture_confidence(s.image, 0.02, mask[None, None], t_xc=0.02)
    assert torch.equal(c2, c4)


@pytest.mark.parametrize("grid, window", [(1, 4), (1, 1), (3, 4), (4, 4), (5, 2)])
def test_window_medians_are_each_windows_lower_median_of_the_values_inside(grid, window):
    from torchiid.priors.texture import _medians

    g = torch.Generator().manual_seed(5)
    r = torch.rand(2, 1, 41, 23, generator=g)  # 41 rows: more than one block of rows
    r[torch.rand(r.shape, generator=g) > 0.7] = float("nan")  # outside a mask
    r[1, 0, 10:30] = float("nan")  # windows with no value inside: 0
    got = _medians(r, window, grid)
    for b in range(2):
        for i in range(got.shape[-2]):
            for j in range(got.shape[-1]):
                y, x = i * grid, j * grid
                part = r[
                    b, 0, max(0, y - window) : y + window + 1, max(0, x - window) : x + window + 1
                ]
                values = part[~part.isnan()].sort().values
                want = values[(values.numel() - 1) // 2] if values.numel() else torch.tensor(0.0)
                assert float(got[b, 0, i, j]) == float(want), (b, i, j)


def test_the_edge_band_is_every_pixel_within_its_reach_of_an_edge():
    from torchiid.priors.texture import _dilate

    edges = (torch.rand(2, 1, 30, 37, generator=torch.Generator().manual_seed(6)) > 0.998).float()
    want = F.max_pool2d(edges, 2 * EDGE_RADIUS + 1, 1, EDGE_RADIUS)
    assert torch.equal(_dilate(edges, EDGE_RADIUS), want) and 0 < want.mean() < 0.9


def test_the_removal_keeps_the_images_dtype_and_agrees_across_it():
    s = textured_plane("wood", "gradient", 64, 64)
    c = texture_confidence(s.image, 0.02, t_xc=0.02)
    single = detexture(s.image.float(), 0.02, confidence=c)
    double = detexture(s.image.double(), 0.02, confidence=c)
    assert single.dtype == torch.float32 and double.dtype == torch.float64
    assert torch.allclose(single.double(), double, rtol=1e-5)
    assert not torch.allclose(double, s.image.double(), rtol=1e-3)  # the grain is taken out
