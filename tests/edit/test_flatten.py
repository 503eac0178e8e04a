"""torchiid.edit.flatten: one flat reflectance colour inside a mask."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit import remove_texture


def _textured(scene, box):
    base = torch.tensor([0.6, 0.3, 0.2], dtype=torch.float64).view(1, 3, 1, 1)
    yy, xx = torch.meshgrid(torch.arange(48), torch.arange(64), indexing="ij")
    checker = (((yy // 3) + (xx // 3)) % 2).to(torch.float64) * 2 - 1  # +-1
    return base, torch.where(box, base * (1 + 0.3 * checker), scene.reflectance)


def test_remove_texture_gives_flat_albedo_times_true_shading(scene, box):
    s = scene.shading
    base, r = _textured(scene, box)
    out, _ = remove_texture(r, s, box)
    inside = box.expand(-1, 3, -1, -1)
    err = (out - base * s)[inside].abs().max()
    assert float(err) < 0.01  # flat albedo x true shading within 0.01 (linear)
    assert torch.equal(out[~inside], (r * s)[~inside])


def test_median_takes_the_majority_colour(scene, box):
    s = scene.shading
    r = scene.reflectance.clone()
    colour = torch.tensor([0.2, 0.7, 0.4], dtype=torch.float64).view(1, 3, 1, 1)
    r = torch.where(box, colour, r)
    r[..., 10:14, 16:20] = 0.95  # a small bright spot inside
    _, by_median = remove_texture(r, s, box, flatten="median")
    _, by_mean = remove_texture(r, s, box, flatten="mean")
    torch.testing.assert_close(by_median[..., 20, 30].view(3), colour.view(3))
    assert float((by_mean[..., 20, 30].view(3) - colour.view(3)).abs().max()) > 0.01


def test_empty_mask_and_unknown_flatten_are_refused(scene, box):
    r, s = scene.reflectance, scene.shading
    with pytest.raises(ParameterError, match="no pixel"):
        remove_texture(r, s, torch.zeros_like(box))
    with pytest.raises(ParameterError, match="flatten"):
        remove_texture(r, s, box, flatten="mode")
