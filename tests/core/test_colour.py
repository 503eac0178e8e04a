import math

import kornia
import numpy as np
import pytest
import torch

from torchiid.core.colour import (
    DECODE_THRESHOLD,
    ENCODE_THRESHOLD,
    decode_lut,
    linear_to_srgb,
    linear_to_srgb_np,
    srgb8_encode_lut,
    srgb_to_linear,
)


def _encode(v: float) -> float:
    """IEC 61966-2-1 in Python floats, clipped to [0, 1]."""
    v = min(max(v, 0.0), 1.0)
    return 12.92 * v if v <= 0.0031308 else 1.055 * math.pow(v, 1 / 2.4) - 0.055


def _decode(v: float) -> float:
    v = min(max(v, 0.0), 1.0)
    return v / 12.92 if v <= 0.04045 else math.pow((v + 0.055) / 1.055, 2.4)


VALUES = [-2.0, -1e-9, 0.0, 1e-12, 1e-6, 0.003, 0.0031308, 0.0032, 0.04045, 0.05, 0.5, 1.0, 1.5]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_curve_of_the_standard(dtype):
    x = torch.tensor(VALUES, dtype=dtype)
    tol = 1e-15 if dtype == torch.float64 else 1e-6
    enc = torch.tensor([_encode(v) for v in VALUES], dtype=torch.float64)
    dec = torch.tensor([_decode(v) for v in VALUES], dtype=torch.float64)
    assert float((linear_to_srgb(x).double() - enc).abs().max()) <= tol
    assert float((srgb_to_linear(x).double() - dec).abs().max()) <= tol
    assert linear_to_srgb(x).dtype == dtype and srgb_to_linear(x).dtype == dtype


def test_known_values_and_continuity_at_the_thresholds():
    assert float(linear_to_srgb(torch.tensor(0.5, dtype=torch.float64))) == pytest.approx(
        0.7353569830524495, abs=1e-15
    )
    assert float(srgb_to_linear(torch.tensor(0.5, dtype=torch.float64))) == pytest.approx(
        0.21404114048223255, abs=1e-15
    )
    lo = ENCODE_THRESHOLD * 12.92
    hi = 1.055 * ENCODE_THRESHOLD ** (1 / 2.4) - 0.055
    assert abs(lo - hi) < 1e-7
    assert abs(DECODE_THRESHOLD / 12.92 - ((DECODE_THRESHOLD + 0.055) / 1.055) ** 2.4) < 1e-7


def test_values_outside_the_unit_range_are_clipped():
    x = torch.tensor([-3.0, -1e-6, 1.0 + 1e-6, 7.0, 1e6])
    one = float(linear_to_srgb(torch.tensor(1.0)))  # 1.055 - 0.055 in float32: 1 - 6e-8
    assert one == pytest.approx(1.0, abs=1e-7)
    assert linear_to_srgb(x).tolist() == [0.0, 0.0, one, one, one]
    assert srgb_to_linear(x).tolist() == [0.0, 0.0, 1.0, 1.0, 1.0]
    np.testing.assert_allclose(linear_to_srgb_np(np.array([-3.0, 7.0])), [0.0, 1.0], atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bit_identical_to_kornia_on_rgb_images(dtype):
    g = torch.Generator().manual_seed(0)
    x = torch.cat([torch.rand(2, 3, 20, 30, generator=g) * 1.4 - 0.2, torch.zeros(1, 3, 20, 30)])
    x = x.to(dtype)
    ref_enc = kornia.color.linear_rgb_to_rgb(x.clamp(0, 1))
    ref_dec = kornia.color.rgb_to_linear_rgb(x.clamp(0, 1))
    assert torch.equal(linear_to_srgb(x), ref_enc)
    assert torch.equal(srgb_to_linear(x), ref_dec)


@pytest.mark.parametrize("shape", [(7,), (5, 6), (3, 5, 6), (2, 1, 5, 6), (2, 3, 5, 6)])
def test_any_shape_the_same_values(shape):
    g = torch.Generator().manual_seed(1)
    x = torch.rand(shape, generator=g, dtype=torch.float64) * 1.2 - 0.1
    flat = x.reshape(-1)
    assert torch.equal(linear_to_srgb(x).reshape(-1), linear_to_srgb(flat))
    assert torch.equal(srgb_to_linear(x).reshape(-1), srgb_to_linear(flat))
    assert linear_to_srgb(x).shape == shape and srgb_to_linear(x).shape == shape


def test_round_trip():
    x = torch.linspace(0, 1, 10001, dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12, rtol=0)
    torch.testing.assert_close(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12, rtol=0)


def test_finite_gradients_also_at_zero():
    x = torch.tensor([0.0, 1e-9, 0.0031308, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert float(x.grad[0]) == pytest.approx(12.92)
    y = torch.tensor([0.0, 0.04045, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    srgb_to_linear(y).sum().backward()
    assert torch.isfinite(y.grad).all()


def test_numpy_version_matches_torch():
    x = np.random.default_rng(0).random((40, 50, 3)) * 1.2 - 0.1
    out = linear_to_srgb_np(x)
    assert out.shape == x.shape and out.dtype == np.float64
    ref = linear_to_srgb(torch.from_numpy(x)).numpy()
    assert np.abs(out - ref).max() <= 1e-15


@pytest.mark.parametrize("depth", [8, 16])
def test_decode_lookup_table(depth):
    n = 1 << depth
    lut = decode_lut(depth)
    assert lut.shape == (n,) and lut.dtype == np.float32 and not lut.flags.writeable
    assert lut is decode_lut(depth) and lut is decode_lut(depth, False)
    assert lut is decode_lut(depth, linear=False)
    exact = np.array([_decode(c / (n - 1)) for c in range(n)])
    assert np.array_equal(lut, exact.astype(np.float32))  # one float32 rounding of the curve
    assert np.all(np.diff(lut) > 0)
    lin = decode_lut(depth, linear=True)
    assert np.array_equal(lin, np.arange(n, dtype=np.float32) / np.float32(n - 1))
    assert not lin.flags.writeable


def test_encode_lookup_table():
    lut = srgb8_encode_lut()
    assert lut.shape == (65536,) and lut.dtype == np.uint8 and not lut.flags.writeable
    assert lut is srgb8_encode_lut()
    assert lut[0] == 0 and lut[65535] == 255 and np.all(np.diff(lut.astype(int)) >= 0)
    codes = np.arange(0, 65536, 97)
    expect = [round(255 * _encode(c / 65535)) for c in codes]
    assert lut[codes].tolist() == expect
    # every 8-bit code decodes and re-encodes to itself through the two tables
    lin16 = np.rint(decode_lut(8).astype(np.float64) * 65535).astype(np.int64)
    assert np.array_equal(lut[lin16], np.arange(256))
