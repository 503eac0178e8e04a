import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.pairs import PairSet
from torchiid.priors.stencil import Stencil


def _dense_pairs(i, j, n):
    m = torch.zeros(len(i), n, dtype=torch.float64)
    for r, (a, b) in enumerate(zip(i.tolist(), j.tolist(), strict=True)):
        m[r, a] += 1
        m[r, b] -= 1
    return m


def test_pairset_matches_dense_per_image():
    torch.manual_seed(0)
    h, w, p = 4, 5, 9
    i = torch.randint(0, h * w, (2, p))
    j = torch.randint(0, h * w, (2, p))
    ps = PairSet(i, j, h, w)
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    wts = torch.rand(2, p, dtype=torch.float64)
    d = ps.difference_matrix(wts).to_dense()
    for b in range(2):
        m = _dense_pairs(i[b], j[b], h * w)
        torch.testing.assert_close(ps.apply(x)[b, 0], m @ x[b].reshape(-1))
        a = m.T @ torch.diag(wts[b]) @ m
        torch.testing.assert_close(ps.laplacian_matvec(wts, x)[b].reshape(-1), a @ x[b].reshape(-1))
        torch.testing.assert_close(ps.laplacian_diagonal(wts)[b].reshape(-1), a.diagonal())
        blk = d[b * p : (b + 1) * p, b * h * w : (b + 1) * h * w]
        torch.testing.assert_close(blk.T @ blk, a)


def test_from_stencil_agrees_with_stencil():
    torch.manual_seed(1)
    st = Stencil.square(6, 7, 5)
    ps = PairSet.from_stencil(st)
    wk = torch.rand(2, st.num_offsets, 6, 7, dtype=torch.float64)
    k, i, _ = st.pair_index()
    wp = wk[:, k, i // 7, i % 7]
    x = torch.randn(2, 1, 6, 7, dtype=torch.float64)
    torch.testing.assert_close(ps.laplacian_matvec(wp, x), st.laplacian_matvec(wk, x))


def test_pairset_errors():
    with pytest.raises(ParameterError, match="empty"):
        PairSet(torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), 4, 4)
    with pytest.raises(ParameterError, match=r"\[0, 16\)"):
        PairSet(torch.tensor([0]), torch.tensor([16]), 4, 4)
    with pytest.raises(ShapeError):
        PairSet(torch.tensor([0, 1]), torch.tensor([1]), 4, 4)
    with pytest.raises(ShapeError, match="integer"):
        PairSet(torch.tensor([0.0]), torch.tensor([1.0]), 4, 4)
    ps = PairSet(torch.tensor([[0], [1]]), torch.tensor([[1], [2]]), 4, 4)
    with pytest.raises(ShapeError, match="batch"):
        ps.apply(torch.zeros(3, 1, 4, 4))
