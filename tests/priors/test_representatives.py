import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.representatives import (
    global_pair_term,
    representative_pixels,
    segment_layout,
)

D = torch.float64


def _labels(b=2, h=9, w=11, seed=0):
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randint(0, 5, (b, 3, 3), generator=g)
    lab = torch.nn.functional.interpolate(coarse[:, None].double(), size=(h, w), mode="nearest")
    return lab[:, 0].long() * 3  # sparse label values (0, 3, 6, ...)


def _check_reps(f, lab, reps, use):
    b, d, h, w = f.shape
    for bi in range(b):
        segs = torch.unique(lab[bi][use[bi]])
        got = reps.index[bi][reps.valid[bi]]
        assert got.numel() == segs.numel()  # one per segment
        assert sorted(reps.label[bi][reps.valid[bi]].tolist()) == segs.tolist()
        for q, s in zip(got.tolist(), reps.label[bi][reps.valid[bi]].tolist(), strict=True):
            inside = (lab[bi].reshape(-1) == s) & use[bi].reshape(-1)
            assert bool(inside[q])  # inside its segment
            fx = f[bi].reshape(d, -1)[:, inside]
            dist = (fx - fx.mean(1, keepdim=True)).square().sum(0)
            dq = (f[bi].reshape(d, -1)[:, q] - fx.mean(1)).square().sum()
            assert float(dq) <= float(dist.min()) + 1e-12  # closest to the segment mean


def test_one_representative_per_segment_closest_to_mean():
    g = torch.Generator().manual_seed(1)
    f = torch.rand(2, 3, 9, 11, generator=g, dtype=D)
    lab = _labels()
    reps = representative_pixels(f, lab)
    _check_reps(f, lab, reps, torch.ones_like(lab, dtype=torch.bool))
    assert reps.counts.tolist() == [int(torch.unique(x).numel()) for x in lab]


def test_sparse_huge_label_ids_give_the_same_representatives():
    g = torch.Generator().manual_seed(4)
    f = torch.rand(2, 3, 9, 11, generator=g, dtype=D)
    lab = _labels()
    dense = representative_pixels(f, lab)
    sparse = representative_pixels(f, lab * 2**40 + 7)  # same segments, ids up to ~2^43
    assert torch.equal(dense.index, sparse.index) and torch.equal(dense.valid, sparse.valid)


def test_mask_and_negative_labels_are_ignored():
    g = torch.Generator().manual_seed(2)
    f = torch.rand(2, 3, 9, 11, generator=g, dtype=D)
    lab = _labels(seed=3)
    lab[:, 0, :] = -1
    mask = torch.rand(2, 1, 9, 11, generator=g) > 0.3
    reps = representative_pixels(f, lab, mask)
    use = mask[:, 0] & (lab >= 0)
    _check_reps(f, lab, reps, use)


@pytest.mark.parametrize("masked", [False, True])
def test_a_layout_kept_across_feature_maps_gives_the_same_representatives(masked):
    g = torch.Generator().manual_seed(6)
    lab = _labels(seed=7)
    mask = torch.rand(2, 1, 9, 11, generator=g) > 0.3 if masked else None
    layout = segment_layout(lab, mask)
    assert layout.dense is not masked  # unmasked: the features are read without a gather
    for _ in range(3):  # new features each time (an alternation's r̄), one layout
        f = torch.rand(2, 3, 9, 11, generator=g, dtype=D)
        ref = representative_pixels(f, lab, mask)
        got = representative_pixels(f, lab, mask, layout=layout)
        for a, b in ((ref.index, got.index), (ref.valid, got.valid), (ref.label, got.label)):
            assert torch.equal(a, b)
        use = (lab >= 0) if mask is None else mask[:, 0] & (lab >= 0)
        _check_reps(f, lab, got, use)
    with pytest.raises(ShapeError, match="layout is for labels of shape"):
        representative_pixels(torch.rand(1, 3, 9, 11), lab[:1], layout=layout)


def test_global_pairs_count_and_weights():
    g = torch.Generator().manual_seed(4)
    f = torch.rand(2, 3, 9, 11, generator=g, dtype=D) * 0.1
    lab = _labels(seed=5)
    reps = representative_pixels(f, lab)
    term = global_pair_term(f, reps, 0.05)
    q = reps.index.shape[1]
    assert term.i.shape == (2, q * (q - 1) // 2)
    for bi in range(2):
        n = int(reps.counts[bi])
        nz = term.weights[bi] > 0
        assert int(nz.sum()) == n * (n - 1) // 2
        ff = f[bi].reshape(3, -1)
        ref = torch.exp(-(ff[:, term.i[bi]] - ff[:, term.j[bi]]).square().sum(0) / (2 * 0.05**2))
        torch.testing.assert_close(term.weights[bi][nz], ref[nz])


def test_errors():
    f = torch.rand(1, 3, 4, 4)
    with pytest.raises(ShapeError, match=r"expected labels of shape \(1, 4, 4\)"):
        representative_pixels(f, torch.zeros(1, 4, 5, dtype=torch.long))
    with pytest.raises(ShapeError, match="expected integer labels"):
        representative_pixels(f, torch.zeros(1, 4, 4))
