"""Small collections for the collection tests: tiny photos, the fast colour Retinex method."""

from __future__ import annotations

import pytest

from collection_helpers import photo


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
