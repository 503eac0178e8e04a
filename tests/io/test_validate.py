"""Validation: files that cannot be images get one-line errors naming the file and problem."""

import cv2
import numpy as np
import pytest

from torchiid.core.exceptions import ImageError
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
