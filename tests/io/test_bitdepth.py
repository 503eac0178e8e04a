"""Bit depth: 8- and 16-bit codes through the sRGB lookup tables, gray, alpha."""

import cv2
import numpy as np
import pytest
import torch

from torchiid.core.colour import decode_lut
from torchiid.io import load_image, srgb_to_linear


def _float_decoding(codes, scale):
    """The curve in float: float32 codes / scale, then srgb_to_linear on a (3, H, W) tensor."""
    x = torch.from_numpy(codes.astype(np.float32) / np.float32(scale)).permute(2, 0, 1)
    return srgb_to_linear(x.contiguous())


def test_every_8bit_code_matches_the_float_decoding(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    rgb = np.stack([codes, codes[::-1], codes.T], axis=-1)
    path = tmp_path / "codes.png"
    assert cv2.imwrite(str(path), rgb[..., ::-1])
    got = load_image(path, min_side=1).image
    assert got.dtype == torch.float32
    assert float((got - _float_decoding(rgb, 255)).abs().max()) <= 1e-6
    exact = torch.from_numpy(rgb.astype(np.float64) / 255).permute(2, 0, 1)
    exact = torch.where(exact <= 0.04045, exact / 12.92, ((exact + 0.055) / 1.055) ** 2.4)
    assert float((got.double() - exact).abs().max()) <= 1e-7  # float32 rounding only


def test_16bit_codes_match_the_float_decoding(tmp_path):
    rng = np.random.default_rng(0)
    sample = np.concatenate(
        [[0, 1, 2, 2650, 2651, 32767, 32768, 65534, 65535], rng.integers(0, 65536, 4087)]
    )
    rgb = np.stack([sample, sample[::-1], np.roll(sample, 7)], axis=-1).astype(np.uint16)
    rgb = rgb.reshape(64, 64, 3)
    path = tmp_path / "codes16.png"
    assert cv2.imwrite(str(path), rgb[..., ::-1])
    got = load_image(path).image
    assert float((got - _float_decoding(rgb, 65535)).abs().max()) <= 1e-6
    lin = load_image(path, linear=True).image  # linear files: exactly code / 65535 in float32
    expect = torch.from_numpy(rgb.astype(np.float32) / np.float32(65535)).permute(2, 0, 1)
    assert torch.equal(lin, expect)


def test_gray_8bit_is_decoded_into_all_three_channels(tmp_path):
    gray = np.tile(np.arange(256, dtype=np.uint8), (64, 1))
    path = tmp_path / "g.png"
    assert cv2.imwrite(str(path), gray)
    got = load_image(path).image
    expect = _float_decoding(np.repeat(gray[..., None], 3, axis=2), 255)
    assert float((got - expect).abs().max()) <= 1e-6
    assert torch.equal(got[0], got[1]) and torch.equal(got[0], got[2])


def test_lookup_tables_are_built_once_and_read_only():
    lut = decode_lut(8, False)
    assert lut is decode_lut(8, False)
    assert lut.dtype == np.float32 and lut.shape == (256,) and not lut.flags.writeable
    assert decode_lut(16, True).shape == (65536,)


@pytest.mark.parametrize(
    ("dtype", "below", "above"), [(np.uint8, 127, 128), (np.uint16, 32767, 32768)]
)
def test_alpha_threshold_is_exactly_one_half(tmp_path, dtype, below, above):
    bgra = np.full((64, 64, 4), below, dtype)
    bgra[:5, :7, 3] = above
    path = tmp_path / "a.png"
    assert cv2.imwrite(str(path), bgra)
    assert int(load_image(path).mask.sum()) == 35
