import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.pairs import PairSet, constraint_matrix
from torchiid.priors.quadratic import StencilQuadratic, SumQuadratic
from torchiid.priors.row_quadratics import ConstraintQuadratic, DiagonalQuadratic, PairQuadratic
from torchiid.priors.stencil import Stencil


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


def test_diagonal_quadratic_is_an_anchor_on_each_pixel():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(2, 1, 3, 4, generator=g, dtype=torch.float64)
    t = torch.randn(2, 1, 3, 4, generator=g, dtype=torch.float64)
    q = DiagonalQuadratic(a, t)
    x = torch.randn(2, 1, 3, 4, generator=g, dtype=torch.float64)
    direct = (a * (x - t) ** 2).flatten(1).sum(1)
    torch.testing.assert_close(q.energy(x) + (a * t**2).flatten(1).sum(1), direct)
    torch.testing.assert_close(q.to_sparse().to_dense(), torch.diag(a.reshape(-1)))
    torch.testing.assert_close(q.diagonal(), a)
    assert torch.equal(DiagonalQuadratic(a).rhs(), torch.zeros_like(a))
    with pytest.raises(ShapeError, match=r"expected weights \(B, 1, H, W\)"):
        DiagonalQuadratic(a[:, 0])
    with pytest.raises(ShapeError, match="expected weights"):
        PairQuadratic(PairSet(torch.tensor([0]), torch.tensor([1]), 3, 4), a.reshape(2, -1))
