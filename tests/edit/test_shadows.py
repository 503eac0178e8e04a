"""torchiid.edit.shadows: the log-shading's range compressed or expanded."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit import SoftenShadows, soften_shadows


def _span(x):
    return float(x.log().amax() - x.log().amin())


def test_soften_shadows(scene, box):
    r, s = scene.reflectance, scene.shading
    _, s0 = soften_shadows(r, s, 0.0)
    torch.testing.assert_close(s0, s)
    _, s1 = soften_shadows(r, s, 0.5)
    assert _span(s1) < 0.6 * _span(s)
    _, s2 = soften_shadows(r, s, -0.5)
    assert _span(s2) > 1.4 * _span(s)
    _, s3 = soften_shadows(r, s, 0.5, mask=box)
    assert torch.equal(s3[~box], s[~box])
    assert float((s3 - s)[box].abs().min()) >= 0 and float((s3 - s)[box].abs().max()) > 0.01


def test_shadows_are_lifted_toward_the_pivot_and_the_pivot_stays(scene):
    r, s = scene.reflectance, scene.shading
    out, soft = soften_shadows(r, s, 0.5, pivot=0.99)
    p = torch.quantile(s.flatten(), 0.99)
    darker = s < p
    assert bool((soft[darker] > s[darker]).all())  # every shadow lifted
    assert bool((soft[darker] <= p + 1e-12).all())  # but not past the pivot
    # with amount 0.5 the log-distance to the pivot halves
    torch.testing.assert_close((p / soft).log(), 0.5 * (p / s).log(), atol=1e-3, rtol=0)
    assert bool((out >= scene.image - 1e-12)[darker.expand(-1, 3, -1, -1)].all())


def test_the_shading_colour_is_kept(scene):
    r, s = scene.reflectance, scene.shading
    coloured = s * torch.tensor([1.0, 0.8, 0.6], dtype=s.dtype).view(1, 3, 1, 1)
    _, soft = soften_shadows(r, coloured, 0.7)
    torch.testing.assert_close(soft / coloured, (soft / coloured)[:, :1].expand(-1, 3, -1, -1))


def test_feathered_mask_blends_its_edge(scene, box):
    r, s = scene.reflectance, scene.shading
    _, hard = soften_shadows(r, s, 0.8, mask=box)
    _, soft = soften_shadows(r, s, 0.8, mask=box, feather=3.0)
    ring = (soft != s) & ~box  # just outside the mask: touched only by the feather
    assert int(ring.sum()) > 0 and torch.equal(hard[ring], s[ring])


@pytest.mark.parametrize("kwargs", [{"amount": 1.5}, {"pivot": 0.0}])
def test_bad_options_are_refused_and_module_matches(scene, kwargs, one_thread):
    r, s = scene.reflectance, scene.shading
    with pytest.raises(ParameterError):
        soften_shadows(r, s, **kwargs)
    got = SoftenShadows(0.3, 0.95)(r, s)
    assert torch.equal(got[1], soften_shadows(r, s, 0.3, pivot=0.95)[1])
