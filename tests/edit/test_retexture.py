"""torchiid.edit.retexture: a texture's colours as the reflectance inside a mask."""

import pytest
import torch
import torch.nn.functional as F

from torchiid.core.exceptions import ParameterError
from torchiid.edit import replace_albedo


@pytest.fixture
def texture():
    return torch.rand(3, 7, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)


@pytest.mark.parametrize("fit", ["tile", "stretch"])
def test_replace_albedo_reproduces_texture_times_shading(scene, box, texture, fit):
    r, s = scene.reflectance, scene.shading
    out, new_r = replace_albedo(r, s, box, texture, fit=fit)
    if fit == "tile":
        want = texture.repeat(1, 3, 6)[None, :, :20, :28]
    else:
        want = F.interpolate(texture[None], size=(20, 28), mode="bilinear", align_corners=False)
    torch.testing.assert_close(new_r[..., 10:30, 16:44], want)
    # the picture: the texture under the scene's own shading inside, the scene outside
    torch.testing.assert_close(out[..., 10:30, 16:44], want * s[..., 10:30, 16:44])
    outside = ~box.expand(-1, 3, -1, -1)
    assert torch.equal(out[outside], scene.image[outside])


def test_tile_scale_enlarges_the_tiles(scene, box):
    r, s = scene.reflectance, scene.shading
    stripes = torch.zeros(3, 2, 2, dtype=torch.float64)
    stripes[:, :, 0] = 1.0  # a white column then a black one
    _, new_r = replace_albedo(r, s, box, stripes, scale=2.0)
    row = new_r[0, 0, 12, 16:28]
    # 2x2 stripes scaled by 2: the pattern repeats every 4 px, from white to black
    assert torch.equal(row[:4], row[4:8]) and torch.equal(row[:4], row[8:12])
    assert float(row[0]) == 1.0 and float(row[3]) == 0.0


@pytest.mark.parametrize("kwargs", [{"fit": "crop"}, {"scale": 0.0}])
def test_bad_options_are_refused(scene, box, texture, kwargs):
    with pytest.raises(ParameterError):
        replace_albedo(scene.reflectance, scene.shading, box, texture, **kwargs)
