"""torchiid.features.roi: RoI-align against torchvision's definition written out."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.roi import RoIAlign, roi_align


def _bilinear(fmap, y, x):
    h, w = fmap.shape[-2:]
    y, x = min(max(y, 0.0), h - 1.0), min(max(x, 0.0), w - 1.0)
    y0, x0 = min(int(y), h - 1), min(int(x), w - 1)
    y1, x1 = min(y0 + 1, h - 1), min(x0 + 1, w - 1)
    ly, lx = y - y0, x - x0
    return (
        fmap[:, y0, x0] * (1 - ly) * (1 - lx)
        + fmap[:, y0, x1] * (1 - ly) * lx
        + fmap[:, y1, x0] * ly * (1 - lx)
        + fmap[:, y1, x1] * ly * lx
    )


def _roi_align_reference(fmap, box, ph, pw, s, scale):
    # torchvision's aligned RoI-align, written out sample by sample, in float64.
    x1, y1, x2, y2 = (v * scale - 0.5 for v in box)
    bh, bw = (y2 - y1) / ph, (x2 - x1) / pw
    out = torch.zeros(fmap.shape[0], ph, pw, dtype=torch.float64)
    for i in range(ph):
        for j in range(pw):
            for a in range(s):
                for b in range(s):
                    y = y1 + (i + (a + 0.5) / s) * bh
                    x = x1 + (j + (b + 0.5) / s) * bw
                    out[:, i, j] += _bilinear(fmap, y, x) / s**2
    return out


def test_roi_align_matches_reference():
    gen = torch.Generator().manual_seed(0)
    fmap = torch.rand(2, 3, 6, 8, dtype=torch.float64, generator=gen)
    boxes = torch.tensor(
        [[0.0, 0.0, 16.0, 12.0], [3.0, 5.0, 9.5, 7.0], [10.0, 2.0, 15.0, 11.5]], dtype=torch.float64
    )
    out = roi_align(fmap, boxes, (2, 3), spatial_scale=0.5, sampling_ratio=2)
    assert out.shape == (2, 3, 3, 2, 3) and out.dtype == torch.float64
    for bi in range(2):
        for n in range(3):
            ref = _roi_align_reference(fmap[bi], boxes[n].tolist(), 2, 3, 2, 0.5)
            torch.testing.assert_close(out[bi, n], ref)
    per_image = roi_align(fmap, boxes.expand(2, -1, -1), (2, 3), 0.5, 2)
    torch.testing.assert_close(per_image, out)
    torch.testing.assert_close(RoIAlign((2, 3), 0.5, 2)(fmap, boxes), out)


def test_roi_align_errors():
    with pytest.raises(ShapeError, match=r"expected boxes of shape \(N, 4\)"):
        roi_align(torch.zeros(1, 2, 4, 4), torch.zeros(3, 5), 2)
    with pytest.raises(ShapeError, match="boxes hold 2 images but features hold 1"):
        roi_align(torch.zeros(1, 2, 4, 4), torch.zeros(2, 3, 4), 2)
    with pytest.raises(ParameterError, match="must be >= 1"):
        roi_align(torch.zeros(1, 2, 4, 4), torch.zeros(3, 4), 0)
