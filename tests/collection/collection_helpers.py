"""Helpers of the collection tests, imported by name (``from collection_helpers import ...``).

They live outside ``conftest.py``: several test folders have a ``conftest.py``, and a test
module that imported one of them by name would make the others collide with it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
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
