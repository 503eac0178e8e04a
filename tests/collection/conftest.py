"""Small collections for the collection tests: tiny photos, the fast colour Retinex method."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

#: options of a fast run (the tests are about the orchestration, not the method)
FAST = ["--method", "retinex", "--no-progress"]


def photo(path: Path, seed: int = 0, w: int = 80, h: int = 64) -> Path:
    """A small real photo (a crop of skimage's chelsea, shifted by ``seed``) as PNG."""
    img = data.chelsea()[40 + 7 * seed : 40 + 7 * seed + 2 * h, 60 : 60 + 2 * w]
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)[..., ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(img))
    return path


@pytest.fixture
def library(tmp_path):
    """A photo library: two IMG_0001.png in different folders, a nested one, a bad file."""
    root = tmp_path / "library"
    photo(root / "2019" / "IMG_0001.png", 0)
    photo(root / "2020" / "IMG_0001.png", 1)
    photo(root / "2020" / "trip" / "IMG_0002.png", 2)
    photo(root / "cover.png", 3)
    (root / "2020" / "broken.png").write_text("not an image")
    (root / "2020" / "notes.txt").write_text("not an image either, and no image suffix")
    return root
