import pytest
import torch

from torchiid.core.stats import _quantile, image_quantile


@pytest.mark.parametrize("interpolation", ["linear", "lower", "higher", "midpoint", "nearest"])
def test_selection_quantile_equals_torch_quantile(interpolation):
    # the ranks are torch.quantile's own (q (n - 1) in float32: at 0.6 M values 0.99 x 599999
    # rounds to 593999.0, so "higher" takes element 593999, not 594000), ties included
    g = torch.Generator().manual_seed(0)
    for n in (1, 2, 10, 1001, 600_000):
        v = torch.rand(n, generator=g)
        v[::7] = 0.5
        for q in (0.0, 0.001, 0.25, 0.5, 0.9, 0.99, 0.999, 1.0):
            want = torch.quantile(v, q, interpolation=interpolation)
            assert torch.equal(_quantile(v, q, interpolation), want), (n, q)


def test_image_quantile_with_mask_nan_and_empty_images():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3, 3, 20, 30, generator=g)
    mask = torch.rand(3, 1, 20, 30, generator=g) > 0.5
    mask[2] = False
    mask[1, 0, 0, 0] = True
    x[1, 0, 0, 0] = float("nan")  # not the selection path: torch.quantile's NaN
    out = image_quantile(x, 0.9, mask, default=7.0)
    inside = x[0][mask[0].expand(3, -1, -1)]
    assert torch.equal(out[0], torch.quantile(inside, 0.9))
    assert torch.isnan(out[1])
    assert float(out[2]) == 7.0
    with pytest.raises(RuntimeError):
        image_quantile(x, 0.5, interpolation="cubic")
