from pathlib import Path

import pytest

from torchiid.core.exceptions import TorchiidError
from torchiid.io import IMAGE_SUFFIXES, collect_inputs


def test_directories_expand_to_their_sorted_image_files(tmp_path):
    d = tmp_path / "photos"
    d.mkdir()
    for name in ("b.JPG", "a.png", "c.npy", "notes.txt", "d.tiff"):
        (d / name).write_bytes(b"")
    (d / "sub.png").mkdir()  # a folder with an image suffix is no image
    single = tmp_path / "x.webp"
    got = collect_inputs([single, d, Path("missing.png")])
    assert got == [single, d / "a.png", d / "b.JPG", d / "c.npy", d / "d.tiff", Path("missing.png")]


def test_a_directory_without_images_is_an_error(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(TorchiidError, match="directory holds no image files") as err:
        collect_inputs([tmp_path])
    assert str(tmp_path) in str(err.value) and ".png" in str(err.value)
    assert "subfolders" not in str(err.value)


def test_a_directory_with_images_only_in_subfolders_points_to_recursive(tmp_path):
    import cv2
    import numpy as np

    (tmp_path / "2024").mkdir()
    cv2.imwrite(str(tmp_path / "2024" / "a.png"), np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(TorchiidError, match="its subfolders do: -r \\(recursive=True in Python\\)"):
        collect_inputs([tmp_path])


def test_suffixes():
    exts = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr", ".npy"}
    assert exts == IMAGE_SUFFIXES  # every format load_image reads, OpenEXR included
