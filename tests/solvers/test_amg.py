import pytest
import torch

from torchiid.core.exceptions import ShapeError

pytest.importorskip("pyamg")

from torchiid.solvers.amg import AMGPreconditioner  # noqa: E402


def _poisson(h, w):
    """The 5-point Laplacian plus a small diagonal, torch sparse (h w, h w)."""
    n = h * w
    idx = torch.arange(n).view(h, w)
    i = torch.cat([idx[:, :-1].reshape(-1), idx[:-1, :].reshape(-1)])
    j = torch.cat([idx[:, 1:].reshape(-1), idx[1:, :].reshape(-1)])
    deg = torch.zeros(n).index_add_(0, i, torch.ones(len(i))).index_add_(0, j, torch.ones(len(j)))
    rows = torch.cat([i, j, torch.arange(n)])
    cols = torch.cat([j, i, torch.arange(n)])
    vals = torch.cat([-torch.ones(2 * len(i)), deg + 1e-2]).double()
    idx = torch.stack([rows, cols])
    return torch.sparse_coo_tensor(idx, vals, (n, n), check_invariants=True).coalesce()


def test_a_v_cycle_from_a_torch_matrix_reduces_the_error():
    a = _poisson(20, 24)
    m = AMGPreconditioner(a, (1, 1, 20, 24), max_coarse=20)
    assert m.operator_complexity() >= 1.0 and m.setup_time > 0
    x = torch.rand(1, 1, 20, 24, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    b = (a @ x.reshape(-1, 1)).view_as(x)
    y = m(b)  # one V-cycle from 0
    assert y.dtype == b.dtype and float((y - x).norm()) < 0.5 * float(x.norm())
    with pytest.raises(ShapeError, match=r"expected \(1, 1, 20, 24\)"):
        m(b[..., :-1])
    with pytest.raises(ShapeError, match="does not fit shape"):
        AMGPreconditioner(a, (1, 1, 20, 20))
