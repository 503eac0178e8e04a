"""torchiid.resample: banded bilinear and guided upsampling against the one-shot filters."""

import torch
import torch.nn.functional as F

from torchiid.resample import (
    GuidedUpsampler,
    bilinear_rows,
    guided_upsample,
    row_bands,
    working_size,
)


def test_bilinear_rows_equal_torch_interpolate():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 1, 13, 17, generator=g, dtype=torch.float64)
    full = F.interpolate(x, size=(50, 41), mode="bilinear", align_corners=False)
    for rows in (slice(0, 7), slice(7, 33), slice(33, 50)):
        assert torch.allclose(bilinear_rows(x, (50, 41), rows), full[:, :, rows], atol=1e-12)


def test_banded_guided_upsampling_equals_the_one_shot_filter():
    g = torch.Generator().manual_seed(2)
    low, guide_low = torch.rand(2, 1, 20, 30, generator=g), torch.rand(2, 1, 20, 30, generator=g)
    guide = torch.rand(2, 1, 80, 120, generator=g)
    # reference: the fast guided filter written out on whole images
    up = GuidedUpsampler(low, guide_low, (80, 120))
    a = F.interpolate(up.a, size=(80, 120), mode="bilinear", align_corners=False)
    b = F.interpolate(up.b, size=(80, 120), mode="bilinear", align_corners=False)
    ref = a * guide + b
    out = guided_upsample(low, guide_low, guide)
    assert torch.allclose(out, ref, atol=1e-5)
    # bands of a few rows (forces many bands) give the same
    bands = [slice(y, min(80, y + 7)) for y in range(0, 80, 7)]
    banded = torch.cat([up.band(r, guide[:, :, r]) for r in bands], 2)
    assert torch.allclose(banded, ref, atol=1e-5)


def test_working_size_keeps_the_aspect_and_never_enlarges():
    assert working_size(384, 512, 512) == (384, 512)
    assert working_size(3000, 4000, 512) == (384, 512)
    assert working_size(300, 400, 0) == (300, 400)  # 0: full resolution


def test_row_bands_cover_every_row_once():
    bands = list(row_bands(5000, 4000))
    rows = [r for band in bands for r in range(*band.indices(5000))]
    assert rows == list(range(5000)) and len(bands) > 1
