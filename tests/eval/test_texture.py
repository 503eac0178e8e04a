import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval import local_linear_residual, texture_in_shading
from torchiid.synthetic_texture import textured_plane


@pytest.fixture(scope="module")
def tiles():
    return textured_plane("tiles", "shadow", 96, 112)


def _gray(x):
    return x.mean(1, keepdim=True)


def test_perfect_shading_scores_zero_and_the_image_scores_one(tiles):
    s = tiles
    assert texture_in_shading(s.shading, s.image, s.shading).item() == pytest.approx(0, abs=1e-9)
    assert texture_in_shading(s.image, s.image, s.shading).item() == pytest.approx(1, abs=1e-9)


@pytest.mark.parametrize("a", [0.25, 0.5, 0.8])
def test_a_shading_that_copies_part_of_the_texture_scores_that_part(tiles, a):
    s = tiles
    partial = s.shading * (_gray(s.image) / s.shading) ** a
    assert texture_in_shading(partial, s.image, s.shading).item() == pytest.approx(a, rel=1e-6)


def test_the_measure_ignores_the_scale_of_both_layers(tiles):
    s = tiles
    half = s.shading * (_gray(s.image) / s.shading) ** 0.5
    base = texture_in_shading(half, s.image, s.shading).item()
    scaled = texture_in_shading(7.0 * half, 0.2 * s.image, 3.0 * s.shading).item()
    assert scaled == pytest.approx(base, rel=1e-9)


def test_without_ground_truth_a_smooth_light_scores_near_zero():
    s = textured_plane("wood", "gradient", 96, 96)
    assert texture_in_shading(s.shading, s.image).item() < 0.01
    assert texture_in_shading(s.image, s.image).item() == pytest.approx(1.0)
    # a soft shadow's edge is not texture, but it is not a plane either: small, not zero
    shadow = textured_plane("wood", "shadow", 256, 256)  # an 8 px soft edge, sigma 3 px
    assert 0.0 < texture_in_shading(shadow.shading, shadow.image).item() < 0.1


def test_error_at_scales_far_above_sigma_does_not_count_but_fine_error_does(tiles):
    s = tiles
    yy = torch.linspace(0, 1, s.image.shape[-2]).view(1, 1, -1, 1)
    xx = torch.linspace(0, 1, s.image.shape[-1]).view(1, 1, 1, -1)
    wrong_light = s.shading * torch.exp(0.8 * yy - 0.5 * xx)  # a wrong, smooth gradient
    assert texture_in_shading(wrong_light, s.image, s.shading).item() < 1e-6
    checker = ((torch.arange(96).view(-1, 1) // 2 + torch.arange(112) // 2) % 2).float()
    wrong_fine = s.shading * torch.exp(0.3 * checker)[None, None]
    assert texture_in_shading(wrong_fine, s.image, s.shading).item() > 0.1


def test_region_restricts_where_texture_counts(tiles):
    s = tiles
    region = torch.zeros(1, 1, 96, 112, dtype=torch.bool)
    region[..., :, :50] = True
    copied = torch.where(region, s.shading, _gray(s.image))  # texture copied outside only
    inside = texture_in_shading(copied, s.image, s.shading, region=region).item()
    assert inside == pytest.approx(0, abs=1e-9)
    outside = texture_in_shading(copied, s.image, s.shading, region=~region).item()
    assert outside == pytest.approx(1, abs=1e-6)  # float32 layers
    assert 0.3 < texture_in_shading(copied, s.image, s.shading).item() < 1


def test_local_linear_residual_removes_planes_up_to_the_region_rim():
    yy = torch.arange(40, dtype=torch.float64).view(1, 1, -1, 1)
    xx = torch.arange(50, dtype=torch.float64).view(1, 1, 1, -1)
    plane = 0.3 + 0.02 * yy - 0.05 * xx
    region = torch.zeros(1, 1, 40, 50, dtype=torch.bool)
    region[..., 5:30, 10:45] = True
    r = local_linear_residual(plane, region, sigma=3.0)
    assert r.abs().max().item() < 1e-9
    assert bool((r[~region] == 0).all())
    bumpy = plane + 0.1 * torch.sin(xx * 2.5)
    assert local_linear_residual(bumpy, region, 3.0).abs().max().item() > 0.05


def test_flat_images_give_nan_and_bad_inputs_fail_clearly():
    flat = torch.full((1, 3, 32, 32), 0.5)
    assert torch.isnan(texture_in_shading(flat[:, :1], flat)).all()
    with pytest.raises(ShapeError, match="shading has shape"):
        texture_in_shading(torch.ones(1, 1, 32, 30), flat)
    with pytest.raises(ParameterError, match="region holds no pixel"):
        texture_in_shading(flat[:, :1], flat, region=torch.zeros(32, 32))
    with pytest.raises(ParameterError, match="must be finite and >= 0"):
        texture_in_shading(-flat[:, :1], flat)
    with pytest.raises(ParameterError, match="sigma"):
        local_linear_residual(flat[:, :1], sigma=0)
