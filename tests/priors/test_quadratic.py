import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.quadratic import StencilQuadratic, SumQuadratic
from torchiid.priors.row_quadratics import DiagonalQuadratic
from torchiid.priors.stencil import Stencil, half_offsets


def _dense(term):
    return term.to_sparse().to_dense()


def _rand(shape, seed, signed=False):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    return x - 0.3 if signed else x


def test_stencil_matvec_matches_assembled_matrix_for_signed_weights():
    st = Stencil(7, 9, half_offsets(5))
    w = _rand((2, st.num_offsets, 7, 9), 0, signed=True)
    term = StencilQuadratic(st, w)
    x = _rand((2, 1, 7, 9), 1)
    ref = (_dense(term) @ x.reshape(-1)).view_as(x)
    torch.testing.assert_close(term.matvec(x), ref)


def test_replaced_weights_are_not_served_from_the_cache():
    st = Stencil.square(6, 5, 3)
    term = StencilQuadratic(st, _rand((1, 4, 6, 5), 2))
    x = _rand((1, 1, 6, 5), 3)
    term.matvec(x)  # fills the per-direction cache
    term.weights = term.weights * 3.0
    torch.testing.assert_close(term.matvec(x), (_dense(term) @ x.reshape(-1)).view_as(x))
    scaled = term.scaled(0.5)
    torch.testing.assert_close(scaled.matvec(x), 0.5 * term.matvec(x))


def test_merged_sum_matches_the_sum_of_matrices():
    st3, st5 = Stencil.square(8, 6, 3), Stencil(8, 6, half_offsets(5))
    a = StencilQuadratic(st3, _rand((1, 4, 8, 6), 4), target=_rand((1, 4, 8, 6), 5))
    b = StencilQuadratic(st5, _rand((1, 12, 8, 6), 6, signed=True))
    total = SumQuadratic([(2.0, a), (0.25, b)])
    x = _rand((1, 1, 8, 6), 7)
    ref = 2.0 * _dense(a) + 0.25 * _dense(b)
    torch.testing.assert_close(total.matvec(x), (ref @ x.reshape(-1)).view_as(x))
    torch.testing.assert_close(total.diagonal().reshape(-1), ref.diagonal())


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
