"""torchiid.edit.intensity: more light in indirectly lit regions."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit import IlluminationIntensity, gaussian, illumination_intensity, merge
from torchiid.edit.intensity import COMBINE


def _stages(scene):
    i, s = scene.image, scene.shading
    sigma = gaussian(s, 4.0) * 0.9 + 0.1 * s.mean()  # a smoother Stage 1 shading
    return sigma, (i / sigma).clamp(0, 1)


def test_illumination_intensity_raises_dark_keeps_bright(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma, rho = _stages(scene)
    for combine in COMBINE:
        out, new_s = illumination_intensity(i, r, s, sigma, rho, 0.5, combine=combine)
        y = s[:, 0]
        dark = y <= torch.quantile(y, 0.1)
        bright = y >= torch.quantile(y, 0.99)
        gain = new_s.mean(1) / merge(i, r, s, sigma, rho).shading.mean(1)
        assert float(gain[dark].mean()) > 1.05, combine
        rel = ((out - i).abs() / i).permute(1, 0, 2, 3)[:, bright]
        assert float(rel.max()) < 0.02, combine  # brightest 1%: within 2%
        assert float((out / i).min()) > 0.97


def test_more_strength_adds_more_light(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma, rho = _stages(scene)
    weak, _ = illumination_intensity(i, r, s, sigma, rho, 0.2)
    strong, _ = illumination_intensity(i, r, s, sigma, rho, 0.8)
    assert bool((strong >= weak - 1e-12).all()) and float((strong - weak).max()) > 0.01
    none, _ = illumination_intensity(i, r, s, sigma, rho, 0.0)
    merged = merge(i, r, s, sigma, rho)
    torch.testing.assert_close(none, merged.reflectance * merged.shading)


def test_unknown_combine_is_refused(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    with pytest.raises(ParameterError, match="combine must be one of"):
        illumination_intensity(i, r, s, s, r, combine="median")


def test_module_twin_matches_the_function(scene, one_thread):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma, rho = _stages(scene)
    got = IlluminationIntensity(0.3, "max", 2.0)(i, r, s, sigma, rho)
    want = illumination_intensity(i, r, s, sigma, rho, 0.3, combine="max", blur=2.0)
    assert torch.equal(got[0], want[0])
