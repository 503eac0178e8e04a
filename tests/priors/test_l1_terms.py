import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.priors.l1_terms import PairL1Term, data_term
from torchiid.priors.reflectance_terms import StencilL1Term
from torchiid.priors.stencil import Stencil

D = torch.float64


def _pair_term(b=2, h=4, w=5, p=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    i = torch.randint(0, h * w, (b, p), generator=g)
    j = torch.randint(0, h * w, (b, p), generator=g)
    wt = torch.rand(b, p, generator=g, dtype=D)
    wt[:, -1] = 0  # a padding pair
    return PairL1Term(i, j, wt, h, w)


def _stencil_term(b=2, h=5, w=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    st = Stencil.square(h, w, 5)
    return StencilL1Term(st, torch.rand(b, st.num_offsets, h, w, generator=g, dtype=D))


def _flat_apply(term, z):
    """apply(z) as (B*P, C) rows in the order of term.matrix()."""
    y = term.apply(z)
    if isinstance(term, StencilL1Term):
        k, i, _ = term.stencil.pair_index()
        w = term.stencil.width
        y = y[:, :, k, i // w, i % w]
    return y.permute(0, 2, 1).reshape(-1, z.shape[1])


@pytest.mark.parametrize("make", [_pair_term, _stencil_term])
def test_operator_matches_sparse_matrix(make):
    term = make()
    b = term.weights.shape[0]
    h, w = (
        (term.height, term.width)
        if isinstance(term, PairL1Term)
        else (term.stencil.height, term.stencil.width)
    )
    g = torch.Generator().manual_seed(3)
    z = torch.rand(b, 3, h, w, generator=g, dtype=D)
    m = term.matrix().to_dense()
    zc = z.permute(0, 2, 3, 1).reshape(-1, 3)  # (B*N, C)
    torch.testing.assert_close(_flat_apply(term, z), m @ zc)
    torch.testing.assert_close(term.l1(z), (m @ zc).abs().reshape(b, -1).sum(1))
    # adjoint: <W M z, y> == <z, (W M)^T y> and equals M^T y of the dense matrix
    y = torch.randn(term.init_state(z).shape, generator=g, dtype=D)
    if isinstance(term, StencilL1Term):
        y = y * term.stencil.valid
    lhs = (term.apply(z) * y).sum()
    rhs = (z * term.adjoint(y)).sum()
    torch.testing.assert_close(lhs, rhs)
    yc = _flat_apply_like(term, y)
    adj = (m.T @ yc).reshape(b, h, w, 3).permute(0, 3, 1, 2)
    torch.testing.assert_close(term.adjoint(y), adj)
    normal = (m.T @ (m @ zc)).reshape(b, h, w, 3).permute(0, 3, 1, 2)
    torch.testing.assert_close(term.normal_matvec(z), normal)
    diag = torch.diagonal(m.T @ m).reshape(b, 1, h, w)
    torch.testing.assert_close(term.normal_diagonal(), diag)


def _flat_apply_like(term, y):
    if isinstance(term, StencilL1Term):
        k, i, _ = term.stencil.pair_index()
        w = term.stencil.width
        y = y[:, :, k, i // w, i % w]
    return y.permute(0, 2, 1).reshape(-1, y.shape[1])


def test_data_term():
    z, r = torch.rand(2, 3, 2, 2, dtype=D), torch.rand(2, 3, 2, 2, dtype=D)
    torch.testing.assert_close(data_term(z, r, 2.0), 2 * ((z - r) ** 2).sum((1, 2, 3)))


def test_pair_term_shapes_must_agree():
    with pytest.raises(ParameterError, match=r"expected i, j, weights of one shape \(B, P\)"):
        PairL1Term(
            torch.zeros(1, 3, dtype=torch.long),
            torch.zeros(1, 2, dtype=torch.long),
            torch.zeros(1, 3),
            2,
            2,
        )
