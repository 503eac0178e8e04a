"""EXIF orientation: load_image and load_mask give the picture as Pillow's exif_transpose does."""

import numpy as np
import pytest
import torch
from PIL import Image, ImageOps

from torchiid.io import linear_to_srgb, load_image, load_mask


def _exif(orientation):
    exif = Image.Exif()
    exif[0x0112] = orientation
    return exif


def _as_uint8(image):
    """(3, H, W) linear float -> (H, W, 3) uint8 code values of a linear=True load."""
    return np.round(image.permute(1, 2, 0).numpy() * 255).astype(np.uint8)


def _pillow_upright(path):
    with Image.open(path) as im:
        return np.asarray(ImageOps.exif_transpose(im))


def _random_rgb(h=20, w=30, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_jpeg_orientation_6_turns_a_wide_photo_upright(tmp_path):
    stored = np.full((64, 96, 3), 40, np.uint8)  # stored W x H = 96 x 64
    stored[:32, :48] = 230  # bright top-left quadrant of the stored pixels
    path = tmp_path / "photo.jpg"
    Image.fromarray(stored).save(path, quality=95, exif=_exif(6))
    loaded = load_image(path)
    assert loaded.orientation == 6
    assert loaded.image.shape == (3, 96, 64)  # (3, W, H)
    srgb = (linear_to_srgb(loaded.image)[0] * 255).numpy()
    # orientation 6 turns the picture 90 degrees clockwise: the quadrant ends up top-right
    assert srgb[:48, 32:].mean() > 200 and srgb[48:, :].mean() < 70 and srgb[:, :32].mean() < 70
    upright = _pillow_upright(path)[..., 0].astype(np.float32)
    assert upright.shape == srgb.shape
    assert np.abs(upright - srgb).mean() < 2  # two JPEG decoders: close, not bit-exact


@pytest.mark.parametrize("orientation", range(1, 9))
def test_png_orientations_match_pillow_exactly(tmp_path, orientation):
    path = tmp_path / f"o{orientation}.png"
    Image.fromarray(_random_rgb()).save(path, exif=_exif(orientation))
    loaded = load_image(path, linear=True, min_side=1)
    assert loaded.orientation == orientation
    np.testing.assert_array_equal(_as_uint8(loaded.image), _pillow_upright(path))


@pytest.mark.parametrize("orientation", range(1, 9))
def test_jpeg_orientations_match_pillow_on_the_same_pixels(tmp_path, orientation):
    import cv2

    path = tmp_path / f"o{orientation}.jpg"
    Image.fromarray(_random_rgb()).save(path, quality=90, exif=_exif(orientation))
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]
    upright = Image.fromarray(np.ascontiguousarray(stored))
    upright.info["exif"] = _exif(orientation).tobytes()
    loaded = load_image(path, linear=True, min_side=1)
    assert loaded.orientation == orientation
    np.testing.assert_array_equal(
        _as_uint8(loaded.image), np.asarray(ImageOps.exif_transpose(upright))
    )


@pytest.mark.parametrize("orientation", range(1, 9))
def test_tiff_orientations_match_pillow_exactly(tmp_path, orientation):
    # OpenCV's TIFF decoder turns some orientations itself (and fails on 5-8 in OpenCV 5)
    path = tmp_path / f"o{orientation}.tif"
    Image.fromarray(_random_rgb()).save(path, exif=_exif(orientation), compression="tiff_lzw")
    loaded = load_image(path, linear=True, min_side=1)
    assert loaded.orientation == orientation
    np.testing.assert_array_equal(_as_uint8(loaded.image), _pillow_upright(path))


def test_16bit_tiff_orientation(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    stored = np.random.default_rng(3).integers(0, 65536, (20, 30, 3), dtype=np.uint16)
    path = tmp_path / "o6.tif"
    tifffile.imwrite(path, stored, photometric="rgb", extratags=[(274, "H", 1, 6, True)])
    loaded = load_image(path, linear=True, min_side=1)
    assert loaded.orientation == 6 and loaded.bit_depth == 16
    expect = np.rot90(stored, -1).astype(np.float32) / 65535
    np.testing.assert_array_equal(loaded.image.permute(1, 2, 0).numpy(), expect)


def test_webp_orientation(tmp_path):
    path = tmp_path / "o8.webp"
    Image.fromarray(_random_rgb()).save(path, lossless=True, exif=_exif(8))
    loaded = load_image(path, linear=True, min_side=1)
    assert loaded.orientation == 8
    np.testing.assert_array_equal(_as_uint8(loaded.image), _pillow_upright(path))


@pytest.mark.parametrize("orientation", [1, 3, 5, 6])
def test_alpha_mask_follows_the_orientation(tmp_path, orientation):
    rgba = np.zeros((20, 30, 4), np.uint8)
    rgba[..., :3] = 128
    rgba[2:6, 3:12, 3] = 255
    path = tmp_path / "a.png"
    Image.fromarray(rgba).save(path, exif=_exif(orientation))
    loaded = load_image(path, min_side=1)
    expect = _pillow_upright(path)[..., 3] > 127
    np.testing.assert_array_equal(loaded.mask[0].numpy(), expect)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_load_mask_orientations_match_pillow(tmp_path, orientation):
    mask = np.zeros((20, 30), np.uint8)
    mask[1:5, 2:9] = 255
    mask[12, 25] = 255
    path = tmp_path / f"m{orientation}.png"
    Image.fromarray(mask).save(path, exif=_exif(orientation))
    got = load_mask(path)
    np.testing.assert_array_equal(got[0].numpy(), _pillow_upright(path) > 0)
    assert got.is_contiguous()


def test_load_mask_shape_check_uses_the_upright_size(tmp_path):
    path = tmp_path / "m.jpg"
    Image.fromarray(np.full((64, 96), 255, np.uint8)).save(path, exif=_exif(6))
    assert load_mask(path, shape=(96, 64)).shape == (1, 96, 64)


def test_no_or_invalid_orientation_means_1(tmp_path):
    arr = _random_rgb()
    plain = tmp_path / "plain.png"
    Image.fromarray(arr).save(plain)
    bogus = tmp_path / "bogus.png"
    Image.fromarray(arr).save(bogus, exif=_exif(9))
    for path in (plain, bogus):
        loaded = load_image(path, linear=True, min_side=1)
        assert loaded.orientation == 1
        np.testing.assert_array_equal(_as_uint8(loaded.image), arr)


def test_output_is_a_contiguous_tensor(tmp_path):
    path = tmp_path / "o7.png"
    Image.fromarray(_random_rgb()).save(path, exif=_exif(7))
    image = load_image(path, min_side=1).image
    assert image.is_contiguous() and image.dtype == torch.float32
