import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.eval import local_linear_residual, texture_in_shading
from torchiid.synthetic_texture import LIGHTS, TEXTURES, smooth_light, texture_set, textured_plane


@pytest.fixture(scope="module")
def planes():
    return texture_set(96, 128)


def test_the_set_holds_every_texture_under_every_light(planes):
    assert sorted(planes) == sorted(f"{t}-{lt}" for t in TEXTURES for lt in LIGHTS)
    assert len(planes) == 10


def test_layers_multiply_to_the_image_and_stay_in_range(planes):
    for name, s in planes.items():
        assert s.image.shape == (1, 3, 96, 128) and s.shading.shape == (1, 1, 96, 128), name
        assert torch.allclose(s.image, s.reflectance * s.shading), name
        assert 0.02 <= s.reflectance.min() and s.reflectance.max() <= 0.95, name
        assert s.shading.max().item() == pytest.approx(1.0) and s.shading.min() > 0.02, name
        assert f"{s.texture}-{s.light}" == name


def test_the_light_is_smooth_and_the_texture_is_fine(planes):
    for name, s in planes.items():
        log_r = s.reflectance.double().mean(1, keepdim=True).log()
        log_s = s.shading.double().log()
        texture = local_linear_residual(log_r, sigma=3.0).square().mean().sqrt().item()
        light = local_linear_residual(log_s, sigma=3.0).square().mean().sqrt().item()
        assert texture > 0.05, name  # fine-scale lightness variation of at least 5%
        assert light < 0.35 * texture, name


def test_each_texture_varies_mostly_in_lightness_within_its_hues(planes):
    # the hard case for a chromaticity-based Retinex term: much of the texture's
    # log-lightness variation comes without a change of chromaticity
    for t in ("tiles", "wood", "fur"):
        r = planes[f"{t}-gradient"].reflectance.double()
        chroma = r / r.sum(1, keepdim=True)
        assert chroma.std(dim=(2, 3)).max() < 0.03, t
        assert r.mean(1).log().std() > 0.08, t


def test_a_shading_equal_to_the_image_scores_one_and_the_truth_zero(planes):
    s = planes["print-shadow"]
    assert texture_in_shading(s.image, s.image, s.shading).item() == pytest.approx(1.0)
    assert texture_in_shading(s.shading, s.image, s.shading).item() == pytest.approx(0.0)


def test_the_shadow_darkens_part_of_the_plane():
    plain = smooth_light("gradient", 64, 64)
    shadow = smooth_light("shadow", 64, 64)
    ratio = shadow / plain * plain.max() / shadow.max()
    assert ratio.min() < 0.45 and ratio.max() > 0.99


def test_seeds_are_deterministic_and_differ():
    a = textured_plane("wood", "gradient", 64, 64, seed=3)
    b = textured_plane("wood", "gradient", 64, 64, seed=3)
    c = textured_plane("wood", "gradient", 64, 64, seed=4)
    assert torch.equal(a.image, b.image)
    assert not torch.equal(a.reflectance, c.reflectance)
    assert textured_plane("fur", "shadow", 64, 64, dtype=torch.float64).image.dtype == (
        torch.float64
    )


def test_bad_names_and_sizes_fail_clearly():
    with pytest.raises(ParameterError, match="unknown texture 'marble'"):
        textured_plane("marble", "gradient")
    with pytest.raises(ParameterError, match="unknown light 'spot'"):
        textured_plane("wood", "spot")
    with pytest.raises(ParameterError, match="at least 32 px"):
        textured_plane("wood", "gradient", 16, 64)
