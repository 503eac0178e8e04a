import numpy as np
import pytest

from torchiid.features.proposal_grouping import leaf_boxes


def _boxes_by_hand(seg: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, 4))
    for label in range(n):
        ys, xs = np.nonzero(seg == label)
        out[label] = [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_leaf_boxes_are_each_labels_extent(seed):
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 30, size=2)
    seg = rng.integers(0, 12, size=(h, w))
    _, seg = np.unique(seg, return_inverse=True)
    seg = seg.reshape(h, w)
    n = int(seg.max()) + 1
    boxes = leaf_boxes(seg, n)
    assert boxes.dtype == np.float64
    np.testing.assert_array_equal(boxes, _boxes_by_hand(seg, n))


def test_leaf_boxes_of_blocks():
    seg = np.zeros((5, 7), dtype=np.int32)
    seg[1:4, 2:6] = 1
    seg[4, 6] = 2
    np.testing.assert_array_equal(leaf_boxes(seg, 3), [[0, 0, 7, 5], [2, 1, 6, 4], [6, 4, 7, 5]])


def test_leaf_boxes_rejects_labels_out_of_range():
    with pytest.raises(ValueError, match="labels must lie"):
        leaf_boxes(np.array([[0, 3]]), 2)
