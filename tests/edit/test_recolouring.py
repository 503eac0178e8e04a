"""torchiid.edit.recolouring: new hue and chroma inside a mask."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit import Recolour, linear_to_lab, recolour
from torchiid.edit.colour import colour_ab


def _q8(x):
    return (x.clamp(0, 1) * 255).round()


def test_recolour_outside_unchanged_shading_kept(scene, box):
    r, s = scene.reflectance, scene.shading
    out, new_r = recolour(r, s, box, hue=60, chroma=1.0)
    outside = ~box.expand(-1, 3, -1, -1)
    assert torch.equal(_q8(out)[outside], _q8(r * s)[outside])
    inside = box.expand(-1, 3, -1, -1)
    assert float((new_r - r)[inside].abs().max()) > 0.05  # it did change
    lab0, lab1 = linear_to_lab(r), linear_to_lab(new_r)
    moved = ~((new_r == 0) | (new_r == 1)).any(1, keepdim=True) & box  # not gamut-clipped
    assert float((lab0[:, :1] - lab1[:, :1])[moved].abs().max()) < 0.05  # L* within 0.05
    # the hue turned by 60 degrees where the colour has chroma and was not clipped
    a0, b0, a1, b1 = lab0[:, 1][moved[:, 0]], lab0[:, 2][moved[:, 0]], lab1[:, 1], lab1[:, 2]
    a1, b1 = a1[moved[:, 0]], b1[moved[:, 0]]
    turn = torch.rad2deg(torch.atan2(b1, a1) - torch.atan2(b0, a0)) % 360
    coloured = torch.hypot(a0, b0) > 5
    assert float((turn[coloured] - 60).abs().max()) < 1.0


def test_zero_chroma_makes_the_region_gray(scene, box):
    r, s = scene.reflectance, scene.shading
    _, gray = recolour(r, s, box, chroma=0.0)
    lab = linear_to_lab(gray)
    assert float(lab[:, 1:][box.expand(-1, 2, -1, -1)].abs().max()) < 0.5


def test_target_colour_sets_the_mean_chroma(scene, box):
    r, s = scene.reflectance, scene.shading
    brown = "#806050"  # inside the gamut: clipping to [0, 1] hardly moves it
    target = colour_ab(brown, r).view(2)

    def mean_ab(x):
        return linear_to_lab(x)[:, 1:][box.expand(-1, 2, -1, -1)].view(2, -1).mean(1)

    assert float((mean_ab(r) - target).abs().max()) > 5  # far from it before
    _, new_r = recolour(r, s, box, colour=brown)
    assert float((mean_ab(new_r) - target).abs().max()) < 1.0


def test_negative_chroma_is_refused_and_module_matches(scene, box, one_thread):
    r, s = scene.reflectance, scene.shading
    with pytest.raises(ParameterError, match="chroma"):
        recolour(r, s, box, chroma=-1.0)
    got = Recolour(hue=30, chroma=0.5)(r, s, box)
    want = recolour(r, s, box, hue=30, chroma=0.5)
    assert torch.equal(got[0], want[0])
