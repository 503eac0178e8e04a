"""Loading: linear RGB from 8-bit, 16-bit and float files, gray, alpha masks."""

import cv2
import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError
from torchiid.io import linear_to_srgb, load_image, load_mask, srgb_to_linear


def _write(path, arr):
    assert cv2.imwrite(str(path), arr)
    return path


def test_srgb_roundtrip_matches_reference_curve():
    x = torch.linspace(0, 1, 101, dtype=torch.float64).view(1, 1, 1, -1).expand(1, 3, 1, -1)
    lin = srgb_to_linear(x)
    ref = torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    assert torch.allclose(lin, ref, atol=1e-6)
    assert torch.allclose(linear_to_srgb(lin), x, atol=1e-6)


def test_8bit_is_decoded_from_srgb(tmp_path):
    arr = np.full((64, 70, 3), 128, np.uint8)
    arr[..., 0] = 255  # BGR on disk: blue channel full
    img = load_image(_write(tmp_path / "a.png", arr))
    assert img.bit_depth == 8 and img.image.shape == (3, 64, 70) and img.mask is None
    assert img.image.dtype == torch.float32
    assert abs(float(img.image[0, 0, 0]) - ((128 / 255 + 0.055) / 1.055) ** 2.4) < 1e-5
    assert float(img.image[2, 0, 0]) == pytest.approx(1.0)  # RGB order restored


def test_16bit_keeps_precision_and_linear_flag(tmp_path):
    arr = np.arange(64 * 64 * 3, dtype=np.uint16).reshape(64, 64, 3) * 5
    img = load_image(_write(tmp_path / "a.png", arr), linear=True)
    assert img.bit_depth == 16 and img.linear_file
    expect = torch.from_numpy(arr[..., ::-1].astype(np.float32) / 65535).permute(2, 0, 1)
    assert torch.allclose(img.image, expect, atol=1e-7)
    # 16 bits survive: neighbouring values differ by 5/65535, far below 8-bit steps
    assert float((img.image[:, 0, 1] - img.image[:, 0, 0]).abs().max()) < 1 / 255


def test_gray_is_promoted_and_alpha_becomes_mask(tmp_path):
    gray = np.full((60, 61), 200, np.uint8)
    img = load_image(_write(tmp_path / "g.png", gray))
    assert img.image.shape == (3, 60, 61)
    assert torch.allclose(img.image[0], img.image[2], atol=1e-6)
    rgba = np.zeros((64, 64, 4), np.uint8)
    rgba[..., 3] = 0
    rgba[10:30, 10:30, 3] = 255
    path = _write(tmp_path / "rgba.png", rgba)
    img = load_image(path)
    assert img.mask.shape == (1, 64, 64) and int(img.mask.sum()) == 400
    with pytest.raises(ImageError, match="alpha channel"):
        load_image(path, alpha="error")
    assert load_image(path, alpha="ignore").mask is None


def test_float_npy_is_linear(tmp_path):
    arr = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32) * 2
    np.save(tmp_path / "f.npy", arr)
    img = load_image(tmp_path / "f.npy")
    assert img.bit_depth == 32 and img.linear_file
    assert torch.allclose(img.image.permute(1, 2, 0), torch.from_numpy(arr))


def test_load_mask(tmp_path):
    m = np.zeros((64, 64), np.uint8)
    m[5:9, 5:9] = 255
    mask = load_mask(_write(tmp_path / "m.png", m), shape=(64, 64))
    assert mask.dtype == torch.bool and int(mask.sum()) == 16
    with pytest.raises(ImageError, match="mask is 64x64 px but the image is 70x64 px"):
        load_mask(tmp_path / "m.png", shape=(64, 70))
    _write(tmp_path / "empty.png", np.zeros((64, 64), np.uint8))
    with pytest.raises(ImageError, match="mask is empty"):
        load_mask(tmp_path / "empty.png")
