import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.priors.lle import (
    STRATEGIES,
    lle_term,
    lle_weights,
    patch_rgb_features,
    select_neighbours,
)


def test_knn_matches_brute_force_and_excludes_self():
    torch.manual_seed(0)
    f = torch.randn(2, 15, 4, dtype=torch.float64)
    idx, ok = select_neighbours(f, k=5)
    assert bool(ok.all())
    for b in range(2):
        for p in range(15):
            d = ((f[b] - f[b, p]) ** 2).sum(1)
            d[p] = float("inf")
            assert set(idx[b, p].tolist()) == set(torch.argsort(d)[:5].tolist())
    r1, _ = select_neighbours(f, k=5, strategy="random", seed=3)
    r2, _ = select_neighbours(f, k=5, strategy="random", seed=3)
    assert torch.equal(r1, r2)
    assert not bool((r1 == torch.arange(15).view(1, -1, 1)).any())
    assert set(STRATEGIES) == {"p1", "p2", "p3", "p4"}


def test_weights_sum_to_one_and_reconstruct_point_in_span():
    torch.manual_seed(1)
    d, k = 12, 5
    nb = torch.randn(1, k, d, dtype=torch.float64)
    true_w = torch.tensor([0.5, 0.3, -0.2, 0.25, 0.15], dtype=torch.float64)
    centre = (true_w.view(1, k, 1) * nb).sum(1, keepdim=True)  # in the neighbours' affine span
    f = torch.cat([centre, nb], 1)  # patch 0 is the centre
    index = torch.arange(1, k + 1).view(1, 1, k).expand(1, k + 1, k).clone()
    w = lle_weights(f, index, reg=1e-9)[0, 0]
    torch.testing.assert_close(w.sum(), torch.tensor(1.0, dtype=torch.float64))
    torch.testing.assert_close(w, true_w, atol=1e-5, rtol=0)
    w3 = lle_weights(f, index, reg=1e-3)[0, 0]
    err = ((w3.view(k, 1) * nb[0]).sum(0) - centre[0, 0]).norm() / centre.norm()
    assert float(err) < 1e-2
    torch.testing.assert_close(w3.sum(), torch.tensor(1.0, dtype=torch.float64))


def test_identical_features_give_uniform_weights():
    f = torch.ones(1, 6, 3)
    idx, ok = select_neighbours(f, k=4)
    w = lle_weights(f, idx, ok)
    torch.testing.assert_close(w, torch.full_like(w, 0.25))


def test_lle_term_rows_match_dense_reference():
    torch.manual_seed(2)
    h, w = 9, 10
    ctr = torch.tensor([[1, 1], [1, 5], [4, 2], [4, 8], [7, 3], [7, 7], [2, 8]])
    f = torch.randn(2, 7, 5, dtype=torch.float64)
    term = lle_term(ctr, f, h, w, k=3)
    idx, ok = select_neighbours(f, k=3)
    wts = lle_weights(f, idx, ok)
    m = torch.zeros(2 * 7, 2 * h * w, dtype=torch.float64)
    for b in range(2):
        for p in range(7):
            m[b * 7 + p, b * h * w + ctr[p, 0] * w + ctr[p, 1]] += 1
            for q in range(3):
                a = idx[b, p, q]
                m[b * 7 + p, b * h * w + ctr[a, 0] * w + ctr[a, 1]] -= wts[b, p, q]
    torch.testing.assert_close(term.matrix.to_dense(), m)
    a = m.T @ m
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    torch.testing.assert_close(term.matvec(x).reshape(-1), a @ x.reshape(-1))
    torch.testing.assert_close(term.to_sparse().to_dense(), a)
    torch.testing.assert_close(term.diagonal().reshape(-1), a.diagonal())
    # rows annihilate constants
    torch.testing.assert_close(term.matvec(torch.ones_like(x)), torch.zeros_like(x))


def test_lle_term_mask_excludes_patches():
    torch.manual_seed(3)
    ctr = torch.tensor([[1, 1], [1, 5], [4, 2], [4, 6], [6, 6]])
    f = torch.randn(1, 5, 3, dtype=torch.float64)
    mask = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    mask[0, 0, 4, 6] = False
    term = lle_term(ctr, f, 8, 8, k=4, mask=mask)
    m = term.matrix.to_dense()
    assert float(m[:, 4 * 8 + 6].abs().max()) == 0.0  # never a neighbour, no row of its own
    torch.testing.assert_close(m[[0, 1, 2, 4]].sum(1), torch.zeros(4, dtype=torch.float64))


def test_patch_rgb_features_match_loop():
    torch.manual_seed(4)
    img = torch.rand(1, 3, 12, 14, dtype=torch.float64)
    ctr = torch.tensor([[0, 0], [6, 7], [11, 13], [3, 10]])
    got = patch_rgb_features(img, ctr, patch_size=5)
    for p, (y, x) in enumerate(ctr.tolist()):
        win = img[0, :, max(0, y - 2) : y + 3, max(0, x - 2) : x + 3]
        torch.testing.assert_close(got[0, p], win.mean((1, 2)))


def test_lle_errors():
    f = torch.randn(1, 4, 3)
    ctr = torch.tensor([[1, 1], [2, 2], [3, 3], [4, 4]])
    with pytest.raises(ShapeError, match="3 patch centres"):
        lle_term(ctr[:3], f, 8, 8)
    with pytest.raises(ParameterError, match="inside"):
        lle_term(ctr * 3, f, 8, 8)
    with pytest.raises(ParameterError, match="strategy"):
        lle_term(ctr, f, 8, 8, neighbours="nearest")
    with pytest.raises(ParameterError, match="at least 2"):
        lle_term(ctr[:1], f[:, :1], 8, 8)
    bad = f.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ImageError, match="NaN"):
        lle_term(ctr, bad, 8, 8)
