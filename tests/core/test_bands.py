"""Bands of rows: a per-pixel function computed band by band gives the whole image's result."""

import pytest
import torch

import torchiid.core.bands as bands
from torchiid.core.bands import by_rows, row_bands
from torchiid.edit.colour import lab_to_linear, linear_to_lab


@pytest.fixture
def small_bands(monkeypatch):
    """Bands of 1000 pixels, so that images of a few thousand pixels are split."""
    monkeypatch.setattr(bands, "CACHE_PIXELS", 1000)


def _layers(h=97, w=83, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(2, 3, h, w, generator=g), torch.rand(2, 1, h, w, generator=g) + 0.1


def test_row_bands_cover_every_row_once():
    rows = list(row_bands(1001, 250, 1000))
    assert [r.start for r in rows] == list(range(0, 1001, 4))
    assert rows[-1].stop == 1001
    assert all(r.stop - r.start == 4 for r in rows[:-1])


def test_arithmetic_by_rows_is_exactly_the_whole_image(small_bands):
    r, s = _layers()
    calls = []

    def fn(r, s):
        calls.append(r.shape[-2])
        return (r * s + 0.25) / (s + 1), s * s - r.mean(1, keepdim=True)

    a, b = by_rows(fn, r, s)
    whole = fn(r, s)
    assert len(calls) == 1 + len(range(0, 97, 12))  # 12 rows of 83 px per band, then whole
    assert a.shape == (2, 3, 97, 83) and b.shape == (2, 1, 97, 83)
    assert torch.equal(a, whole[0]) and torch.equal(b, whole[1])


def test_one_tensor_out_and_colour_conversions(small_bands):
    # float64: pow's vectorised and scalar paths may round the last bit differently at a
    # band's end, and the Lab round trip (cubes, cube roots, a shift out of gamut) magnifies
    # a float32 last bit to a few units (7.6e-7 of 0.12 on an AVX-512 Xeon)
    r, _ = _layers(seed=1)
    r = r.double()

    def roundtrip(x):
        shift = torch.tensor([0.0, 20.0, -10.0], dtype=x.dtype).view(1, 3, 1, 1)
        return lab_to_linear(linear_to_lab(x) + shift)

    banded, whole = by_rows(roundtrip, r), roundtrip(r)
    assert isinstance(banded, torch.Tensor) and banded.dtype == torch.float64
    assert torch.allclose(banded, whole, rtol=1e-12, atol=1e-14)


def test_images_of_up_to_two_bands_go_whole():
    r, s = _layers()
    calls = []
    out = by_rows(lambda r, s: calls.append(1) or r * s, r, s)
    assert calls == [1] and torch.equal(out, r * s)


def test_images_of_different_sizes_are_refused():
    with pytest.raises(ValueError, match="one height and width"):
        by_rows(torch.add, torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 9))
