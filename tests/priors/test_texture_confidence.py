import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.params import Parameters
from torchiid.priors.texture import REMOVAL_SIGMA, detexture, texture_confidence
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


def test_t_x_is_off_by_default_and_reaches_the_shading_group():
    assert Parameters().shading.t_x == 0.0
    assert all(Parameters.preset(p).shading.t_x == 0.0 for p in ("paper", "print", "converged"))
    assert Parameters.preset("texture").shading.t_x == 0.02
    assert Parameters().replace(t_x=0.05).alternation(3)[0].t_x == 0.05


@pytest.mark.parametrize("texture", ["tiles", "wood", "fur"])
def test_stage1_shading_keeps_less_texture_with_t_x(texture):
    from torchiid.eval import texture_in_shading
    from torchiid.model import decompose

    s = textured_plane(texture, "gradient", 96, 96)
    p = Parameters().replace(iterations=2, use_sc=False, use_sm=False, use_rm=False, use_rg=False)
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
