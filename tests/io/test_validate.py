"""Validation: files that cannot be images get one-line errors naming the file and problem."""

import cv2
import numpy as np
import pytest

from torchiid.core.exceptions import ImageError, InputWarning
from torchiid.io import load_image


def _write(path, arr):
    assert cv2.imwrite(str(path), arr)
    return path


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("missing.png", None, "no such file"),
        ("empty.png", lambda p: p.write_bytes(b""), "is empty"),
        ("text.png", lambda p: p.write_text("hello, not a picture"), "not an image"),
        ("small.png", lambda p: _write(p, np.zeros((20, 80, 3), np.uint8)), "at least 60 px"),
        ("nan.npy", lambda p: np.save(p, np.full((64, 64, 3), np.nan, np.float32)), "NaN"),
        ("zero.npy", lambda p: np.save(p, np.zeros((0, 64, 3), np.float32)), "zero size"),
        ("five.npy", lambda p: np.save(p, np.zeros((64, 64, 5), np.float32)), "5 channels"),
        ("neg.npy", lambda p: np.save(p, -np.ones((64, 64, 3), np.float32)), "negative"),
    ],
)
def test_bad_files_get_one_line_errors(tmp_path, name, make, message):
    path = tmp_path / name
    if make is not None:
        make(path)
    with pytest.raises(ImageError, match=message) as info:
        load_image(path)
    text = str(info.value)
    assert name in text and "\n" not in text


def test_directory_is_rejected(tmp_path):
    with pytest.raises(ImageError, match="is a directory"):
        load_image(tmp_path)


def _float_photo(seed=0):
    return np.random.default_rng(seed).uniform(0.1, 1.0, (80, 96, 3)).astype(np.float32)


def test_a_few_negative_values_of_a_float_file_are_set_to_0_with_a_warning(tmp_path):
    ring = _float_photo()
    ring[5, 5, 0], ring[6, 7, 2] = -0.02, -3.0  # a reconstruction filter's ringing
    np.save(tmp_path / "ring.npy", ring)
    with pytest.warns(InputWarning, match=r"ring\.npy: 2 negative values \(down to -3\) set to 0"):
        loaded = load_image(tmp_path / "ring.npy")
    assert (loaded.negatives, loaded.lowest) == (2, -3.0)
    assert float(loaded.image.min()) == 0.0
    ring[ring < 0] = 0  # and nothing else changed
    assert np.array_equal(loaded.image.permute(1, 2, 0).numpy(), ring)


def test_shallow_noise_around_0_is_set_to_0_however_many_pixels_it_touches(tmp_path):
    dark = _float_photo()
    dark[:40] = np.random.default_rng(1).normal(0.0, 0.002, (40, 96, 3))  # black level removed
    np.save(tmp_path / "dark.npy", dark)
    with pytest.warns(InputWarning, match="negative values"):
        loaded = load_image(tmp_path / "dark.npy")
    assert loaded.negatives == int((dark < 0).sum()) > 0.1 * dark.size


def test_a_signed_float_file_is_refused(tmp_path):
    signed = _float_photo()
    signed[:40] -= 0.5  # a difference image: many values, deep below 0
    np.save(tmp_path / "signed.npy", signed)
    refused = r"signed\.npy: has negative values \(\d+\.\d% of its values, down to -0\.3999\)"
    with pytest.raises(ImageError, match=refused):
        load_image(tmp_path / "signed.npy")


def test_a_float_file_without_negatives_loads_without_a_warning(tmp_path, recwarn):
    np.save(tmp_path / "plain.npy", _float_photo())
    loaded = load_image(tmp_path / "plain.npy")
    assert (loaded.negatives, loaded.lowest) == (0, 0.0) and not recwarn.list


def test_the_declared_size_comes_from_the_header_without_decoding(tmp_path):
    from torchiid.io.decode import declared_size

    rgb = np.zeros((70, 90, 3), np.uint8)
    for name in ("a.png", "a.jpg", "a.tif", "a.webp", "a.bmp"):
        _write(tmp_path / name, rgb)
        assert declared_size(tmp_path / name) == (70, 90), name
    np.save(tmp_path / "a.npy", np.zeros((70, 90, 3), np.float32))
    assert declared_size(tmp_path / "a.npy") == (70, 90)
    from torchiid.io import save_image

    save_image(tmp_path / "a.exr", np.ones((70, 90), np.float32), "exr")
    assert declared_size(tmp_path / "a.exr") == (70, 90)
    # a header that declares 3e9 pixels (beyond Pillow's own guard) and holds none
    import struct
    import zlib

    ihdr = b"IHDR" + struct.pack(">IIBBBBB", 60000, 50000, 8, 2, 0, 0, 0)
    crc = struct.pack(">I", zlib.crc32(ihdr))
    end = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))
    head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + crc
    (tmp_path / "big.png").write_bytes(head + end)
    assert declared_size(tmp_path / "big.png") == (50000, 60000)
    (tmp_path / "notes.png").write_text("not a picture")
    assert declared_size(tmp_path / "notes.png") is None
    assert declared_size(tmp_path / "missing.png") is None
