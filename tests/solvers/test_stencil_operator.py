import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.pairs import PairSet, constraint_matrix
from torchiid.priors.quadratic import (
    ConstraintQuadratic,
    DiagonalQuadratic,
    PairQuadratic,
    QuadraticTerm,
    StencilQuadratic,
    SumQuadratic,
)
from torchiid.priors.stencil import Stencil, half_offsets
from torchiid.solvers.stencil_operator import StencilOperator

B, H, W = 2, 7, 9


def _rand(shape, seed):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def mixed_system():
    """Every kind of term from_quadratic takes: 3x3 and 5x5 stencils, rows, pairs, a diagonal."""
    st3, st5 = Stencil.square(H, W, 3), Stencil(H, W, half_offsets(5))
    rows = torch.tensor([[0, 0, 1, 1]] * B)
    cols = torch.tensor([[3, 40, 7, 62], [5, 11, 50, 9]])
    vals = torch.tensor([[1.0, -1.0, 0.5, -0.5]] * B, dtype=torch.float64)
    pairs = PairSet(torch.tensor([0, 10, 20]), torch.tensor([62, 33, 41]), H, W)
    return SumQuadratic(
        [
            (1.0, StencilQuadratic(st3, _rand((B, 4, H, W), 0))),
            (0.5, StencilQuadratic(st5, _rand((B, 12, H, W), 1) - 0.2)),
            (2.0, ConstraintQuadratic(constraint_matrix(rows, cols, vals, 2, H, W), (B, 1, H, W))),
            (0.3, PairQuadratic(pairs, _rand((B, 3), 2))),
            (1.0, DiagonalQuadratic(_rand((B, 1, H, W), 3) + 0.1)),
        ]
    )


def test_from_quadratic_is_the_assembled_system():
    total = mixed_system()
    extra = _rand((B, 1, H, W), 4)
    op = StencilOperator.from_quadratic(total, extra)
    dense = total.to_sparse().to_dense() + torch.diag(extra.reshape(-1))
    blocks = torch.block_diag(*op.to_dense())
    torch.testing.assert_close(blocks, dense)
    x = _rand((B, 2, H, W), 5)  # two probe channels
    flat = x.permute(1, 0, 2, 3).reshape(2, -1)
    want = (flat @ dense).view(2, B, H, W).permute(1, 0, 2, 3)
    torch.testing.assert_close(op.matvec(x), want)
    torch.testing.assert_close(op.diagonal().reshape(-1), dense.diagonal())
    csr = op.to_scipy()
    torch.testing.assert_close(torch.from_numpy(csr.toarray()), dense)
    assert op.radius == 2 and op.numel == H * W and op.local().factors == []


def test_a_mask_restricts_every_term_to_the_pixels_inside():
    total = mixed_system()
    mask = _rand((B, 1, H, W), 6) > 0.3
    op = StencilOperator.from_quadratic(total, mask=mask)
    dm = torch.diag(mask.reshape(-1).double())
    want = dm @ total.to_sparse().to_dense() @ dm
    torch.testing.assert_close(torch.block_diag(*op.to_dense()), want)


def test_terms_without_a_stencil_form_and_bad_shapes_are_refused():
    class Opaque(QuadraticTerm):
        shape = (1, 1, 4, 4)
        dtype = torch.float64
        device = torch.device("cpu")

    with pytest.raises(ShapeError, match="Opaque has no stencil or factored form"):
        StencilOperator.from_quadratic(Opaque())
    a = torch.zeros(1, 4, 5, 5)
    with pytest.raises(ShapeError, match="half offsets"):
        StencilOperator([(0, -1)] + half_offsets(3)[1:], a, torch.ones(1, 1, 5, 5))
    with pytest.raises(ShapeError, match="inconsistent stencil shapes"):
        StencilOperator(half_offsets(3), a, torch.ones(1, 1, 4, 5))
    op = StencilOperator(half_offsets(3), a, torch.ones(1, 1, 5, 5))
    with pytest.raises(ShapeError, match=r"expected x \(B=1, C, 5, 5\)"):
        op.matvec(torch.ones(1, 1, 5, 4))
