"""The fused CPU iteration of pcg against the torch ops' iteration."""

import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.kernel_runtime import compiled
from torchiid.solvers import pcg_fused
from torchiid.solvers.pcg import pcg, pcg_callable

numba = pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(compiled() is None, reason="compiled kernels are off")


def _stencil_problem(shape, dtype, seed=0, easy_last=False):
    """An SPD image operator (a weighted 5-point Laplacian plus a positive diagonal);
    ``easy_last``: the last image's diagonal dominates (it converges in fewer iterations)."""
    g = torch.Generator().manual_seed(seed)
    d = (torch.rand(shape, generator=g, dtype=torch.float64) + 0.05).to(dtype)
    if easy_last:
        d[-1] += 20
    wx = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    wy = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    wx[..., -1] = 0
    wy[..., -1, :] = 0

    def mv(x):
        out = d * x
        fx = wx * (x - x.roll(-1, dims=-1))
        fy = wy * (x - x.roll(-1, dims=-2))
        return out + fx - fx.roll(1, dims=-1) + fy - fy.roll(1, dims=-2)

    diag = d + wx + wx.roll(1, dims=-1) + wy + wy.roll(1, dims=-2)
    b = torch.randn(shape, generator=g, dtype=torch.float64).to(dtype)
    return mv, b, 1 / diag


def _torch_only(monkeypatch):
    monkeypatch.setattr(pcg_fused, "applies", lambda *args: False)


@pytest.mark.parametrize("jacobi", [True, False])
def test_fused_iteration_matches_the_torch_ops(monkeypatch, jacobi):
    # two images that stop at different iterations, sides that are not whole chunks
    mv, b, minv = _stencil_problem((2, 1, 70, 130), torch.float64, easy_last=True)
    pre = minv if jacobi else None
    assert pcg_fused.applies(pre, b, b, b)
    fused = pcg(mv, b, precond=pre, tol=1e-9, max_iter=400)
    _torch_only(monkeypatch)
    ref = pcg(mv, b, precond=pre, tol=1e-9, max_iter=400)
    assert fused.converged and ref.converged
    assert torch.equal(fused.item_iterations, ref.item_iterations)
    assert int(fused.item_iterations[1]) < int(fused.item_iterations[0])
    torch.testing.assert_close(fused.x, ref.x, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fused.r, ref.r, rtol=1e-6, atol=1e-12)
    torch.testing.assert_close(fused.residual, ref.residual, rtol=1e-5, atol=1e-15)


def test_fused_float32_stops_where_the_torch_ops_do(monkeypatch):
    mv, b, minv = _stencil_problem((1, 1, 90, 100), torch.float32, seed=3)
    capped = pcg(mv, b, precond=minv, tol=1e-12, max_iter=25, warn=False)
    conv = pcg(mv, b, precond=minv, tol=1e-4, max_iter=500)
    _torch_only(monkeypatch)
    capped_ref = pcg(mv, b, precond=minv, tol=1e-12, max_iter=25, warn=False)
    conv_ref = pcg(mv, b, precond=minv, tol=1e-4, max_iter=500)
    assert capped.iterations == capped_ref.iterations == 25
    torch.testing.assert_close(capped.x, capped_ref.x, rtol=1e-4, atol=1e-5)
    assert conv.converged and conv_ref.converged
    assert abs(conv.iterations - conv_ref.iterations) <= 1
    true = (b - mv(conv.x)).norm() / b.norm()
    assert float(true) <= 1e-4


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba has one thread here")
def test_fused_result_does_not_depend_on_threads_or_batch():
    # enough chunks for numba's pool (a 1 x 1 x 200 x 300 image is 15 chunks)
    mv, b, minv = _stencil_problem((2, 1, 200, 300), torch.float32, seed=1)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = pcg(mv, b, precond=minv, tol=1e-5, max_iter=60, warn=False)
        torch.set_num_threads(2)
        two = pcg(mv, b, precond=minv, tol=1e-5, max_iter=60, warn=False)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one.x, two.x) and torch.equal(one.residual, two.residual)
    # the operator acts per image, so the first image alone gives the same bits
    mv1, b1, minv1 = _stencil_problem((2, 1, 200, 300), torch.float32, seed=1)
    alone = pcg(
        lambda x: mv1(torch.cat([x, x]))[:1], b1[:1], precond=minv1[:1], tol=1e-5,
        max_iter=60, warn=False,
    )  # fmt: skip
    assert torch.equal(alone.x[0], two.x[0])


def test_fused_breakdown_and_history(monkeypatch):
    indefinite = torch.tensor([1.0, -1.0, 2.0], dtype=torch.float64)
    b = torch.ones(2, 3, dtype=torch.float64)

    def mv(x):
        out = x * indefinite
        out[1] = 2 * x[1]  # the second item is SPD
        return out

    res = pcg(mv, b, max_iter=50, warn=False)
    assert not res.converged and float(res.residual[1]) <= 1e-5
    assert int(res.item_iterations[0]) < 50  # stopped on the breakdown, not at the cap
    with monkeypatch.context() as m:
        _torch_only(m)
        ref = pcg(mv, b, max_iter=50, warn=False)
    assert torch.equal(res.item_iterations, ref.item_iterations)
    # the history records the fused iteration's residuals, kept where an item stopped
    mv2, b2, minv2 = _stencil_problem((2, 1, 40, 50), torch.float64, seed=2, easy_last=True)
    hist = pcg_callable(mv2, b2, precond=minv2, tol=1e-8, max_iter=300)
    direct = pcg(mv2, b2, precond=minv2, tol=1e-8, max_iter=300)
    assert torch.equal(hist.x, direct.x)
    stop = int(hist.item_iterations[1])
    assert stop < hist.iterations
    assert bool((hist.history[stop:, 1] == hist.history[stop, 1]).all())
    _torch_only(monkeypatch)
    ref = pcg_callable(mv2, b2, precond=minv2, tol=1e-8, max_iter=300)
    torch.testing.assert_close(hist.history, ref.history, rtol=1e-6, atol=1e-14)


def test_where_the_fused_iteration_applies():
    b = torch.ones(1, 5)
    assert pcg_fused.applies(None, b, b, b) and pcg_fused.applies(torch.ones(1, 5), b, b, b)
    assert not pcg_fused.applies(lambda r: r, b, b, b)  # a callable preconditioner
    assert not pcg_fused.applies(None, b.half(), b.half(), b.half())
    assert not pcg_fused.applies(None, b, b.double(), b)
    assert not pcg_fused.applies(None, b, b, b.double())  # a start residual of another dtype
    assert not pcg_fused.applies(torch.ones(1, 5, dtype=torch.float64), b, b, b)
    assert not pcg_fused.applies(None, torch.ones(0, 5), torch.ones(0, 5), torch.ones(0, 5))
    grad = torch.ones(1, 5, requires_grad=True)
    assert not pcg_fused.applies(None, grad, grad, grad)
    assert not pcg_fused.applies(None, b, b, grad)  # the operator's output records a graph
    with torch.no_grad():
        assert pcg_fused.applies(None, grad, grad, grad)


def test_solves_the_fused_iteration_cannot_take_run_the_torch_ops():
    # an operator whose output requires grad, a start residual of another dtype, no items
    w = torch.full((2, 8), 2.0, requires_grad=True)
    res = pcg(lambda v: w * v, torch.ones(2, 8), tol=1e-10)
    assert res.converged
    torch.testing.assert_close(res.x.detach(), torch.full((2, 8), 0.5))
    b = torch.ones(2, 8)
    res = pcg(lambda v: 2 * v, b, r0=b.double(), tol=1e-10)
    assert res.converged
    empty = pcg_callable(lambda v: v, torch.ones(0, 5))
    assert empty.x.shape == (0, 5)


def test_an_operator_of_the_wrong_shape_is_an_error():
    with pytest.raises(ShapeError, match="operator's output"):
        pcg(lambda v: 2 * v[:1], torch.ones(2, 5, dtype=torch.float64), max_iter=3)


@pytest.mark.parametrize("jacobi", [True, False])
def test_restart_from_the_true_residual_matches_the_torch_ops(monkeypatch, jacobi):
    # a wrong start residual: the recursive residual reaches the tolerance first, the true
    # one does not, and each item restarts its direction from the true residual
    mv, b, minv = _stencil_problem((3, 1, 30, 40), torch.float64, seed=5, easy_last=True)
    pre = minv if jacobi else None
    x0 = torch.zeros_like(b)
    wrong = b + 0.3 * torch.randn(b.shape, generator=torch.Generator().manual_seed(9),
                                   dtype=b.dtype)  # fmt: skip
    fused = pcg(mv, b, x0=x0, precond=pre, r0=wrong, tol=1e-8, max_iter=500)
    _torch_only(monkeypatch)
    ref = pcg(mv, b, x0=x0, precond=pre, r0=wrong, tol=1e-8, max_iter=500)
    assert fused.converged and ref.converged
    # the answer solves the system, not the wrong residual's
    true = (b - mv(fused.x)).flatten(1).norm(dim=1) / b.flatten(1).norm(dim=1)
    assert float(true.max()) <= 1e-8
    assert torch.equal(fused.item_iterations, ref.item_iterations)
    torch.testing.assert_close(fused.x, ref.x, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fused.r, ref.r, rtol=1e-6, atol=1e-14)


def test_kernels_against_numpy():
    from torchiid.solvers import pcg_kernels as k

    rng = np.random.default_rng(0)
    n = k.CHUNK * 2 + 77  # a partial last chunk
    x, r, p, ap, m = (rng.standard_normal((3, n)).astype(np.float32) for _ in range(5))
    alpha = np.array([0.5, -1.0, 0.0], dtype=np.float32)
    nc = k.chunks(n)
    for fn in (k.dots, k.dots_parallel):
        parts = np.empty((3, nc))
        fn(p, ap, parts)
        np.testing.assert_allclose(parts.sum(1), (p.astype(float) * ap).sum(1), rtol=1e-12)
    for minv in (m, np.zeros((0, 0), np.float32)):
        for fn in (k.update, k.update_parallel):
            xs, rs = x.copy(), r.copy()
            sums = np.empty((2, 3, nc))
            fn(xs, rs, p, ap, minv, alpha, sums)
            r_ref = r - alpha[:, None] * ap
            z_ref = r_ref * minv if minv.size else r_ref
            np.testing.assert_allclose(xs, x + alpha[:, None] * p, rtol=1e-6)
            np.testing.assert_allclose(rs, r_ref, rtol=1e-6)
            np.testing.assert_allclose(sums[0].sum(1), (rs.astype(float) * z_ref).sum(1), rtol=1e-6)
            np.testing.assert_allclose(sums[1].sum(1), (rs.astype(float) ** 2).sum(1), rtol=1e-6)
        for fn in (k.direction, k.direction_parallel):
            ps = p.copy()
            fn(ps, r, minv, alpha)
            z = r * minv if minv.size else r
            np.testing.assert_allclose(ps, z + alpha[:, None] * p, rtol=1e-6)
    assert k.chunks(0) == 1 and k.chunks(k.CHUNK) == 1 and k.chunks(k.CHUNK + 1) == 2


def test_pcg_module_keeps_the_torch_iteration_for_other_preconditioners(monkeypatch):
    # a callable preconditioner runs the torch ops (the fused passes need a diagonal)
    def not_here(*args):
        raise AssertionError("the fused iteration ran")

    monkeypatch.setattr(pcg_fused, "iterate", not_here)
    calls = []

    def precond(r):
        calls.append(1)
        return r / 2

    b = torch.ones(1, 4, dtype=torch.float64)
    res = pcg(lambda x: 2 * x, b, precond=precond, tol=1e-10)
    assert res.converged and calls
    with pytest.raises(AssertionError, match="fused"):
        pcg(lambda x: 2 * x, b, precond=torch.full_like(b, 0.5))
