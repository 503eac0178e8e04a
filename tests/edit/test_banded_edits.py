"""The edits computed band by band of rows (large photos) give the whole image's result."""

import torch

import torchiid.core.bands as bands
from torchiid.edit import gaussian, illumination_colour, illumination_intensity, merge
from torchiid.edit.shadows import soften_shadows


def _edits(scene, box):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = gaussian(s, 3.0)
    rho = (i / sigma).clamp(0, 1)
    m = merge(i, r, s, sigma, rho)
    return {
        "merge": (m.reflectance, m.shading, m.c, m.c1, m.c2, m.sparse, m.detailed),
        "intensity": illumination_intensity(i, r, s, sigma, rho, 0.7),
        "intensity e2": illumination_intensity(i, r, s, sigma, rho, 0.7, combine="e2"),
        "soften": soften_shadows(r, s, 0.6),
        "soften in a feathered region": soften_shadows(r, s, -0.5, mask=box, feather=2.0),
        "light colour": illumination_colour(r, s, "#3366ff", 0.8),
    }


def test_banded_edits_equal_the_whole_image(scene, box, monkeypatch):
    whole = _edits(scene, box)  # 48 x 64 px: one band
    monkeypatch.setattr(bands, "CACHE_PIXELS", 200)  # bands of 3 rows
    banded = _edits(scene, box)
    for name, outputs in whole.items():
        assert len(banded[name]) == len(outputs)
        for a, b in zip(banded[name], outputs, strict=True):
            assert a.shape == b.shape, name
            # exp, log and pow may round their last bit differently at a band's end; CIELab's
            # curve steps by about 1e-7 at its threshold (kornia's 7.787 slope), and such a bit
            # can cross it
            rtol = 1e-6 if name == "light colour" else 1e-12
            torch.testing.assert_close(
                a, b, rtol=rtol, atol=1e-14, msg=lambda m, n=name: f"{n}: {m}"
            )
