from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch
from skimage import data, transform

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.segmentation import (
    felzenszwalb_segments,
    graph_segmentation,
    segmentation_backend,
    start_felzenszwalb_segments,
)
from torchiid.synthetic import mondrian


@pytest.fixture(scope="module")
def coffee():
    return transform.resize(data.coffee(), (96, 128), anti_aliasing=True)  # sRGB floats


def test_backend_is_opencv_contrib():
    """The package depends on opencv-contrib-python-headless, so this fails by design on an
    environment where plain opencv-python shadows it (the fallback is for such installs)."""
    assert segmentation_backend() == "opencv"


def test_falls_back_to_skimage_with_one_warning(monkeypatch, caplog):
    import cv2

    monkeypatch.delattr(cv2, "ximgproc")
    segmentation_backend.cache_clear()
    try:
        with caplog.at_level("WARNING", logger="torchiid.features.segmentation"):
            assert segmentation_backend() == "skimage"
            assert segmentation_backend() == "skimage"
            labels = graph_segmentation(np.zeros((20, 30, 3)), scale=100, min_size=50)
        assert labels.shape == (20, 30)
        warnings = [r for r in caplog.records if "opencv-contrib" in r.getMessage()]
        assert len(warnings) == 1
    finally:
        segmentation_backend.cache_clear()


@pytest.mark.parametrize("backend", ["opencv", "skimage"])
def test_labels_are_compact_and_respect_min_size(coffee, backend):
    labels = graph_segmentation(coffee, scale=100, sigma=0.8, min_size=30, backend=backend)
    assert labels.shape == coffee.shape[:2] and labels.dtype == np.int64
    counts = np.bincount(labels.reshape(-1))
    assert labels.min() == 0 and (counts > 0).all()  # labels 0..n-1, none empty
    assert counts.min() >= 30
    # larger k gives fewer, larger segments
    coarse = graph_segmentation(coffee, scale=800, sigma=0.8, min_size=30, backend=backend)
    assert coarse.max() < labels.max()


def test_backends_agree_on_segment_statistics(coffee):
    a = graph_segmentation(coffee, scale=100, min_size=30, backend="opencv")
    b = graph_segmentation(coffee, scale=100, min_size=30, backend="skimage")
    na, nb = a.max() + 1, b.max() + 1
    assert 0.7 < na / nb < 1.4  # same algorithm, different smoothing kernels and tie order
    # most pixel pairs that one backend puts together the other does too (sampled pairs)
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, a.size, (2, 20000))
    same_a, same_b = a.reshape(-1)[i] == a.reshape(-1)[j], b.reshape(-1)[i] == b.reshape(-1)[j]
    assert (same_a == same_b).mean() > 0.9


def test_errors():
    with pytest.raises(ShapeError, match="HxWxC"):
        graph_segmentation(np.zeros((10, 10)), scale=100)
    with pytest.raises(ParameterError, match="scale"):
        graph_segmentation(np.zeros((10, 10, 3)), scale=0)
    with pytest.raises(ParameterError, match="backend"):
        graph_segmentation(np.zeros((10, 10, 3)), scale=10, backend="x")


def test_felzenszwalb_segments_batch():
    s = mondrian(40, 48, batch=2, seed=1)
    seg = felzenszwalb_segments(s.image, scale=100, min_size=20)
    assert seg.shape == (2, 40, 48) and seg.dtype == torch.long
    assert int(seg.min()) == 0 and int(seg.max()) >= 2
    one = felzenszwalb_segments(s.image[1:], scale=100, min_size=20)
    assert torch.equal(seg[1:], one)


def test_felzenszwalb_segments_in_the_background_and_on_srgb_input():
    from torchiid.core.colour import linear_to_srgb

    s = mondrian(40, 48, batch=2, seed=1)
    seg = felzenszwalb_segments(s.image, scale=100, min_size=20)
    with ThreadPoolExecutor(max_workers=1) as pool:
        later = start_felzenszwalb_segments(s.image, scale=100, min_size=20, executor=pool)
        assert torch.equal(later(), seg)
    srgb = linear_to_srgb(s.image)
    assert torch.equal(felzenszwalb_segments(srgb, linear=False, scale=100, min_size=20), seg)
