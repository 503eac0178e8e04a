import torch

from torchiid.priors.stencil import half_offsets
from torchiid.solvers.hierarchy import aggregation, galerkin
from torchiid.solvers.stencil_operator import StencilOperator


def _operator(h=14, w=17, seed=3):
    """A random symmetric 5x5 stencil (signed weights), a diagonal and two non-local rows."""
    g = torch.Generator().manual_seed(seed)
    offs = half_offsets(5)
    a = -torch.rand(1, len(offs), h, w, generator=g, dtype=torch.float64)
    a[:, 3] *= -0.05  # a few positive off-diagonals
    for k, (dy, dx) in enumerate(offs):  # zero the entries whose partner is outside
        valid = torch.zeros(h, w, dtype=torch.bool)
        valid[max(0, -dy) : h - max(0, dy), max(0, -dx) : w - max(0, dx)] = True
        a[0, k][~valid] = 0
    d = 25 + torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)  # SPD
    rows = torch.tensor([0, 0, 0, 1, 1, 1])
    cols = torch.tensor([5, 100, 200, 17, 18, 230])
    vals = torch.tensor([1.0, -0.6, -0.4, 1.0, -0.5, -0.5], dtype=torch.float64)
    m = torch.sparse_coo_tensor(
        torch.stack([rows, cols]), vals, (2, h * w), check_invariants=False
    ).coalesce()
    return StencilOperator(offs, a, d, [(m, torch.tensor([0.7, 1.3], dtype=torch.float64))])


def test_galerkin_coarse_operator_is_exact():
    op = _operator()
    h, w = op.height, op.width
    tr = aggregation(op, block=3, lanczos_steps=15, omega=4.0 / 3.0)
    assert tr.coarse_shape == (5, 6)
    coarse = galerkin(op, tr)
    n_c = coarse.numel
    eye = torch.eye(n_c, dtype=torch.float64).view(n_c, 1, 5, 6).transpose(0, 1)
    p = tr.prolong(eye).reshape(n_c, h * w).T  # (N, Nc)
    want = p.T @ op.to_dense()[0] @ p
    torch.testing.assert_close(coarse.to_dense()[0], want, rtol=1e-10, atol=1e-10)
    # the non-local rows stay factored on the coarse grid
    assert len(coarse.factors) == 1 and coarse.factors[0][0].shape == (2, n_c)
    # restriction is the transpose of prolongation
    r = torch.randn(1, 1, h, w, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    torch.testing.assert_close(tr.restrict(r).reshape(-1), p.T @ r.reshape(-1))


def test_tentative_prolongation_copies_and_sums_over_aggregates():
    op = _operator(h=7, w=8)
    tr = aggregation(op, block=3, lanczos_steps=5, omega=4.0 / 3.0)
    assert tr.coarse_shape == (3, 3)
    xc = torch.arange(9, dtype=torch.float64).view(1, 1, 3, 3)
    up = tr.up(xc)
    assert up.shape == (1, 1, 7, 8) and float(up[0, 0, 6, 7]) == 8.0
    # P_t^T is the adjoint of P_t, on the cut-off last row and column too
    r = torch.rand(1, 1, 7, 8, dtype=torch.float64)
    torch.testing.assert_close((up * r).sum(), (xc * tr.sum_down(r)).sum())
    half = tr.to(torch.float32)
    assert half.local.dtype == torch.float32 and half.omega.dtype == torch.float32
