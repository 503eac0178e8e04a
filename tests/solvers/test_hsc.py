import numpy as np
import scipy.sparse as sp
import torch

from torchiid.solvers.hsc import HSCPreconditioner, _grounded_graph


def _system(h, w, seed):
    """A grid Laplacian with random weights, a small ground and a few positive couplings."""
    rng = np.random.default_rng(seed)
    n = h * w
    idx = np.arange(n).reshape(h, w)
    i = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    j = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    wt = rng.uniform(0.1, 1.0, len(i))
    lap = sp.csr_matrix((np.concatenate([-wt, -wt]), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
    lap = lap - sp.diags(np.asarray(lap.sum(axis=1)).ravel())
    pos = sp.csr_matrix(([0.05, 0.05], ([0, 5], [5, 0])), shape=(n, n))  # matting-like
    return (-lap + pos + sp.diags(np.full(n, 1e-2) + 0.1)).tocsr()


def test_grounded_graph_dominates_the_matrix():
    a = _system(5, 6, 0)
    wts, ground = _grounded_graph(a)
    assert wts.min() >= 0 and ground.min() >= 0
    lap = sp.diags(np.asarray(wts.sum(axis=1)).ravel() + ground) - wts
    x = np.random.default_rng(1).standard_normal((a.shape[0], 5))
    assert np.all(np.einsum("ij,ij->j", x, lap @ x) >= np.einsum("ij,ij->j", x, a @ x) - 1e-12)


def test_small_systems_are_solved_exactly_and_large_ones_preconditioned_spd():
    a = _system(6, 7, 2)
    exact = HSCPreconditioner(a, (1, 1, 6, 7))  # under max_coarse: the dense solve only
    assert exact.levels == []
    b = torch.rand(1, 1, 6, 7, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    want = torch.linalg.solve(torch.from_numpy(_grounded(a)), b.reshape(-1))
    torch.testing.assert_close(exact(b).reshape(-1), want, rtol=1e-4, atol=1e-6)
    big = _system(24, 20, 4)
    m = HSCPreconditioner(big, (1, 1, 24, 20), max_coarse=40)
    assert len(m.levels) >= 2 and len(m.lost) == len(m.levels)
    g = torch.Generator().manual_seed(5)
    x, y = (torch.randn(1, 1, 24, 20, generator=g, dtype=torch.float64) for _ in range(2))
    mx, my = m(x), m(y)
    assert abs(float((x * my).sum() - (y * mx).sum())) <= 1e-9 * float(x.norm() * my.norm())
    assert float((x * mx).sum()) > 0


def _grounded(a):
    wts, ground = _grounded_graph(a)
    dense = -wts.toarray()
    np.fill_diagonal(dense, np.asarray(wts.sum(axis=1)).ravel() + ground)
    return dense
