"""The sRGB lookup-table decoding and the permissions of written files."""

import os
import stat

import cv2
import numpy as np
import pytest
import torch

import torchiid.io.image as image_module
from torchiid.core.colour import decode_lut
from torchiid.io import load_image, save_image, save_uint8, srgb_to_linear


def _previous_decoding(codes, scale):
    """The former path: float32 codes / scale, then srgb_to_linear on a (3, H, W) tensor."""
    x = torch.from_numpy(codes.astype(np.float32) / np.float32(scale)).permute(2, 0, 1)
    return srgb_to_linear(x.contiguous())


def test_every_8bit_code_matches_the_previous_decoding(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    rgb = np.stack([codes, codes[::-1], codes.T], axis=-1)
    path = tmp_path / "codes.png"
    assert cv2.imwrite(str(path), rgb[..., ::-1])
    got = load_image(path, min_side=1).image
    assert got.dtype == torch.float32
    assert float((got - _previous_decoding(rgb, 255)).abs().max()) <= 1e-6
    exact = torch.from_numpy(rgb.astype(np.float64) / 255).permute(2, 0, 1)
    exact = torch.where(exact <= 0.04045, exact / 12.92, ((exact + 0.055) / 1.055) ** 2.4)
    assert float((got.double() - exact).abs().max()) <= 1e-7  # float32 rounding only


def test_16bit_codes_match_the_previous_decoding(tmp_path):
    rng = np.random.default_rng(0)
    sample = np.concatenate(
        [[0, 1, 2, 2650, 2651, 32767, 32768, 65534, 65535], rng.integers(0, 65536, 4087)]
    )
    rgb = np.stack([sample, sample[::-1], np.roll(sample, 7)], axis=-1).astype(np.uint16)
    rgb = rgb.reshape(64, 64, 3)
    path = tmp_path / "codes16.png"
    assert cv2.imwrite(str(path), rgb[..., ::-1])
    got = load_image(path).image
    assert float((got - _previous_decoding(rgb, 65535)).abs().max()) <= 1e-6
    lin = load_image(path, linear=True).image  # linear files: exactly code / 65535 in float32
    expect = torch.from_numpy(rgb.astype(np.float32) / np.float32(65535)).permute(2, 0, 1)
    assert torch.equal(lin, expect)


def test_gray_8bit_is_decoded_into_all_three_channels(tmp_path):
    gray = np.tile(np.arange(256, dtype=np.uint8), (64, 1))
    path = tmp_path / "g.png"
    assert cv2.imwrite(str(path), gray)
    got = load_image(path).image
    expect = _previous_decoding(np.repeat(gray[..., None], 3, axis=2), 255)
    assert float((got - expect).abs().max()) <= 1e-6
    assert torch.equal(got[0], got[1]) and torch.equal(got[0], got[2])


def test_lookup_tables_are_built_once_and_read_only():
    lut = decode_lut(8, False)
    assert lut is decode_lut(8, False)
    assert lut.dtype == np.float32 and lut.shape == (256,) and not lut.flags.writeable
    assert decode_lut(16, True).shape == (65536,)


@pytest.fixture
def umask():
    previous = os.umask(0o022)
    os.umask(previous)

    def set_umask(value):
        os.umask(value)

    yield set_umask
    os.umask(previous)


def _mode(path):
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize(("mask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_saved_files_follow_the_umask(tmp_path, umask, mask, mode):
    umask(mask)
    x = torch.rand(3, 8, 8)
    written = [
        save_image(tmp_path / "a.png", x),
        save_image(tmp_path / "a.npy", x, "npy"),
        save_image(tmp_path / "a.exr", x, "exr"),
        save_uint8(tmp_path / "u.png", np.zeros((8, 8, 3), np.uint8)),
    ]
    assert [_mode(p) for p in written] == [mode] * 4


def test_umask_fallback_probe_restores_the_umask(tmp_path, umask, monkeypatch):
    real_open = open

    def no_proc(file, *args, **kwargs):
        if str(file) == "/proc/self/status":
            raise OSError("no /proc here")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(image_module, "open", no_proc, raising=False)
    monkeypatch.setattr(image_module, "_probed_umask", None)
    umask(0o027)
    path = save_image(tmp_path / "b.npy", torch.ones(3, 4, 4), "npy")
    assert _mode(path) == 0o640
    assert os.umask(0o027) == 0o027  # left as it was


@pytest.mark.parametrize(
    ("dtype", "below", "above"), [(np.uint8, 127, 128), (np.uint16, 32767, 32768)]
)
def test_alpha_threshold_is_exactly_one_half(tmp_path, dtype, below, above):
    bgra = np.full((64, 64, 4), below, dtype)
    bgra[:5, :7, 3] = above
    path = tmp_path / "a.png"
    assert cv2.imwrite(str(path), bgra)
    assert int(load_image(path).mask.sum()) == 35
