"""``torchiid features``: pictures of a photo's Stage 0 features."""

import cv2
import numpy as np
import pytest
from skimage import data

from torchiid.cli import main


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    d = tmp_path_factory.mktemp("photos")
    cat = cv2.resize(data.chelsea(), (96, 72), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(d / "cat.png"), cat[..., ::-1])
    return d


def test_features_command_writes_pictures_and_timings(photos, tmp_path, capsys):
    out = tmp_path / "feat"
    assert main(["features", str(photos / "cat.png"), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "selective search" in printed and "patch features" in printed
    for name in ("cat-gpca.png", "cat-proposals.png", "cat-patch-grid.png"):
        img = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.dtype == np.uint8 and img.ndim == 3
    assert main(["features", str(photos / "cat.png"), "-o", str(out)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
