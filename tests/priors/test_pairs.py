import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.pairs import PairSet, constraint_matrix
from torchiid.priors.quadratic import (
    ConstraintQuadratic,
    DiagonalQuadratic,
    PairQuadratic,
    StencilQuadratic,
    SumQuadratic,
)
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


def test_all_pairs_and_pair_quadratic_rhs():
    idx = torch.tensor([[0, 5, 7, 11], [1, 2, 3, 4]])
    ps = PairSet.all_pairs(idx, 3, 4)
    assert ps.num_pairs == 6
    assert bool((ps.i != ps.j).all())
    wts = torch.rand(2, 6, dtype=torch.float64)
    c = torch.randn(2, 6, dtype=torch.float64)
    q = PairQuadratic(ps, wts, c)
    x = torch.randn(2, 1, 3, 4, dtype=torch.float64)
    direct = (wts * (ps.apply(x)[:, 0] - c) ** 2).sum(1)
    torch.testing.assert_close(q.energy(x) + (wts * c**2).sum(1), direct)
    torch.testing.assert_close(q.to_sparse().to_dense() @ x.reshape(-1), q.matvec(x).reshape(-1))


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


def test_constraint_quadratic_matches_dense():
    torch.manual_seed(2)
    h, w, r = 3, 4, 5
    rows = torch.randint(0, r, (2, 12))
    cols = torch.randint(0, h * w, (2, 12))
    vals = torch.randn(2, 12, dtype=torch.float64)
    m = constraint_matrix(rows, cols, vals, r, h, w).to_dense()
    ref = torch.zeros(2 * r, 2 * h * w, dtype=torch.float64)
    for b in range(2):
        for e in range(12):
            ref[b * r + rows[b, e], b * h * w + cols[b, e]] += vals[b, e]
    torch.testing.assert_close(m, ref)
    wts = torch.rand(2 * r, dtype=torch.float64)
    c = torch.randn(2 * r, dtype=torch.float64)
    q = ConstraintQuadratic(constraint_matrix(rows, cols, vals, r, h, w), (2, 1, h, w), wts, c)
    a = ref.T @ torch.diag(wts) @ ref
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    torch.testing.assert_close(q.matvec(x).reshape(-1), a @ x.reshape(-1))
    # accumulated into a given tensor (how SumQuadratic adds it to a stencil's product)
    y0 = torch.randn(2, 1, h, w, dtype=torch.float64)
    got = q.add_matvec(x, y0.clone(), 0.7)
    torch.testing.assert_close(got.reshape(-1), y0.reshape(-1) + 0.7 * (a @ x.reshape(-1)))
    st = Stencil.square(h, w, 3)
    sq = StencilQuadratic(st, torch.rand(2, st.num_offsets, h, w, dtype=torch.float64))
    total = SumQuadratic([(1.5, sq), (0.7, q)])
    dense = 1.5 * sq.to_sparse().to_dense() + 0.7 * a
    torch.testing.assert_close(total.matvec(x).reshape(-1), dense @ x.reshape(-1))
    torch.testing.assert_close(q.diagonal().reshape(-1), a.diagonal())
    torch.testing.assert_close(q.rhs().reshape(-1), ref.T @ (wts * c))
    torch.testing.assert_close(q.to_sparse().to_dense(), a)
    with pytest.raises(ParameterError, match="empty"):
        constraint_matrix(rows[:, :0], cols[:, :0], vals[:, :0], r, h, w)


def test_sum_quadratic_merges_stencils_and_matches_sparse():
    torch.manual_seed(3)
    h, w = 4, 5
    st = Stencil.square(h, w, 3)
    t1 = StencilQuadratic(
        st,
        torch.rand(1, 4, h, w, dtype=torch.float64),
        torch.randn(1, 4, h, w, dtype=torch.float64),
    )
    t2 = StencilQuadratic(st, torch.rand(1, 4, h, w, dtype=torch.float64))
    t3 = DiagonalQuadratic(
        torch.rand(1, 1, h, w, dtype=torch.float64), torch.randn(1, 1, h, w, dtype=torch.float64)
    )
    s = SumQuadratic([(2.0, t1), (0.5, t2), (3.0, t3), (1.0, None), (0.0, t2)])
    assert len(s.terms) == 2  # the two stencil terms merged
    a = (
        2 * t1.to_sparse().to_dense()
        + 0.5 * t2.to_sparse().to_dense()
        + 3 * t3.to_sparse().to_dense()
    )
    x = torch.randn(1, 1, h, w, dtype=torch.float64)
    torch.testing.assert_close(s.matvec(x).reshape(-1), a @ x.reshape(-1))
    torch.testing.assert_close(s.to_sparse().to_dense(), a)
    torch.testing.assert_close(s.diagonal().reshape(-1), a.diagonal())
    torch.testing.assert_close(s.rhs(), 2 * t1.rhs() + 3 * t3.rhs())
    with pytest.raises(ShapeError):
        SumQuadratic([(1.0, None)])
