"""torchiid.edit.tint: illumination colour near the light regions."""

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from torchiid.core.exceptions import ParameterError
from torchiid.edit import IlluminationColour, illumination_colour, light_weights
from torchiid.edit.tint import _distance_to_nearest_zero


def test_illumination_colour_far_pixels_unchanged(scene):
    r, s = scene.reflectance, scene.shading
    out, new_s = illumination_colour(r, s, "red", 1.0, percentile=0.95, radius=0.2)
    w = light_weights(s, 0.95, 0.2)
    far = (w == 0).expand(-1, 3, -1, -1)
    assert int(far.sum()) > 100
    torch.testing.assert_close(out[far], scene.image[far], atol=1e-12, rtol=0)
    near = (w == 1)[:, 0]
    assert float((new_s[:, 0] - new_s[:, 1])[near].mean()) > 0.05  # reddish light there
    out_g, new_sg = illumination_colour(r, s, "0,255,0", 1.0, radius=0.2)
    assert float((new_sg[:, 1] - new_sg[:, 0])[near].mean()) > 0.05


def test_strength_zero_changes_nothing_and_white_tint_keeps_gray(scene):
    r, s = scene.reflectance, scene.shading
    _, same = illumination_colour(r, s, "blue", 0.0)
    torch.testing.assert_close(same, s.expand(-1, 3, -1, -1), atol=1e-6, rtol=1e-6)
    _, white = illumination_colour(r, s, "white", 1.0)
    assert float((white[:, 0] - white[:, 2]).abs().max()) < 1e-4


def test_light_weights_fall_from_one_to_zero_with_distance(scene):
    s = scene.shading
    w = light_weights(s, 0.9, 0.25)
    y = s[:, 0]
    light = y >= torch.quantile(y.flatten(), 0.9)
    assert torch.equal(w[:, 0][light], torch.ones_like(w[:, 0][light]))
    assert float(w.min()) == 0.0 and float(w.max()) == 1.0
    # a wider radius reaches farther: never lower weights
    assert bool((light_weights(s, 0.9, 0.5) >= w - 1e-6).all())


def test_light_weights_are_the_same_on_every_call(scene):
    # the weights of one shading must not change from call to call (OpenCV's IPP transform
    # gives some of this scene's distances one float32 step off on every other call)
    first = light_weights(scene.shading, 0.9, 0.3)
    for _ in range(8):
        assert torch.equal(light_weights(scene.shading, 0.9, 0.3), first)


def test_distances_are_exact_and_ipp_stays_on_in_the_caller():
    rng = np.random.default_rng(0)
    before = cv2.ipp.useIPP()
    for h, w, p in [(48, 64, 0.9), (37, 121, 0.98), (150, 90, 0.6), (1, 30, 0.9)]:
        mask = (rng.random((h, w)) < p).astype(np.uint8)
        mask[h // 2, w // 3] = 0
        exact = ndimage.distance_transform_edt(mask).astype(np.float32)
        assert np.array_equal(_distance_to_nearest_zero(mask), exact)
    assert cv2.ipp.useIPP() == before


@pytest.mark.parametrize("kwargs", [{"percentile": 1.0}, {"percentile": 0.0}, {"radius": 0.0}])
def test_light_weights_check_their_options(scene, kwargs):
    with pytest.raises(ParameterError):
        light_weights(scene.shading, **kwargs)


def test_module_twin_matches_the_function(scene, one_thread):
    r, s = scene.reflectance, scene.shading
    got = IlluminationColour("cyan", 0.5, 0.9, 0.3)(r, s)
    want = illumination_colour(r, s, "cyan", 0.5, percentile=0.9, radius=0.3)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
