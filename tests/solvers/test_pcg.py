import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ConvergenceWarning, ImageError, ShapeError
from torchiid.solvers import pcg_fused
from torchiid.solvers.pcg import pcg, pcg_callable


@pytest.fixture(autouse=True, params=["fused", "torch"])
def iteration(request, monkeypatch):
    """Every test runs the fused CPU iteration where it applies, and the torch ops'."""
    if request.param == "torch":
        monkeypatch.setattr(pcg_fused, "applies", lambda *args: False)
    return request.param


def _spd(n, seed, cond=100.0):
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, n, generator=g, dtype=torch.float64))
    ev = torch.logspace(0, torch.log10(torch.tensor(cond)).item(), n, dtype=torch.float64)
    d = torch.rand(n, generator=g, dtype=torch.float64) * 10 + 0.1  # badly scaled rows
    a = q @ torch.diag(ev) @ q.T
    return d.sqrt().view(-1, 1) * a * d.sqrt().view(1, -1)


def _batch_matvec(mats):
    def mv(x):
        return torch.stack([m @ xi for m, xi in zip(mats, x, strict=True)])

    return mv


def test_matches_linalg_solve_with_and_without_jacobi():
    mats = [_spd(20, s) for s in range(3)]
    b = torch.randn(3, 20, dtype=torch.float64)
    ref = torch.stack([torch.linalg.solve(m, bi) for m, bi in zip(mats, b, strict=True)])
    for precond in (None, torch.stack([1 / m.diagonal() for m in mats])):
        res = pcg(_batch_matvec(mats), b, precond=precond, tol=1e-10, max_iter=500)
        assert res.converged
        torch.testing.assert_close(res.x, ref, atol=1e-7, rtol=1e-7)
        assert float(res.residual.max()) <= 1e-10


def test_jacobi_helps_on_badly_scaled_system():
    mats = [_spd(40, 7)]
    b = torch.randn(1, 40, dtype=torch.float64)
    plain = pcg(_batch_matvec(mats), b, tol=1e-8, max_iter=1000)
    jac = pcg(
        _batch_matvec(mats), b, precond=1 / mats[0].diagonal().view(1, -1), tol=1e-8, max_iter=1000
    )
    assert jac.iterations < plain.iterations


def test_batched_equals_per_item():
    mats = [_spd(15, s, cond=1e3) for s in (1, 2)]
    b = torch.randn(2, 15, dtype=torch.float64)
    pre = torch.stack([1 / m.diagonal() for m in mats])
    both = pcg(_batch_matvec(mats), b, precond=pre, tol=1e-9)
    for k in range(2):
        one = pcg(_batch_matvec(mats[k : k + 1]), b[k : k + 1], precond=pre[k : k + 1], tol=1e-9)
        torch.testing.assert_close(both.x[k], one.x[0], atol=1e-7, rtol=0)
        # round-off at the stopping boundary may shift the count by one
        assert abs(int(both.item_iterations[k]) - one.iterations) <= 1


def test_warm_start_needs_fewer_iterations():
    mats = [_spd(120, 3, cond=1e4)]
    b = torch.randn(1, 120, dtype=torch.float64)
    pre = 1 / mats[0].diagonal().view(1, -1)
    cold = pcg(_batch_matvec(mats), b, precond=pre, tol=1e-9, max_iter=2000)
    rough = pcg(_batch_matvec(mats), b, precond=pre, tol=1e-4, max_iter=2000)
    warm = pcg(_batch_matvec(mats), b, x0=rough.x, precond=pre, tol=1e-9, max_iter=2000)
    assert warm.converged and warm.iterations < cold.iterations
    torch.testing.assert_close(warm.x, cold.x, atol=1e-6, rtol=0)


def test_float32_converged_means_true_residual_reached():
    mats = [_spd(60, 4, cond=1e4).float()]
    b = torch.randn(1, 60)
    res = pcg(
        _batch_matvec(mats),
        b,
        precond=1 / mats[0].diagonal().view(1, -1),
        tol=1e-5,
        max_iter=2000,
        warn=False,
    )
    true = (b[0] - mats[0] @ res.x[0]).norm() / b[0].norm()
    torch.testing.assert_close(res.residual[0], true, rtol=1e-3, atol=1e-7)
    if res.converged:
        assert float(true) <= 1e-5


def test_warns_when_tolerance_missed_and_on_breakdown():
    mats = [_spd(30, 5, cond=1e4)]
    b = torch.randn(1, 30, dtype=torch.float64)
    with pytest.warns(ConvergenceWarning, match="relative residual"):
        res = pcg(_batch_matvec(mats), b, tol=1e-12, max_iter=3)
    assert not res.converged and res.iterations == 3
    indefinite = [torch.diag(torch.tensor([1.0, -1.0, 2.0], dtype=torch.float64))]
    with pytest.warns(ConvergenceWarning, match="not positive definite"):
        res = pcg(_batch_matvec(indefinite), torch.ones(1, 3, dtype=torch.float64), max_iter=50)
    assert not res.converged


def test_errors_and_zero_rhs():
    mv = _batch_matvec([torch.eye(4, dtype=torch.float64)])
    with pytest.raises(ShapeError):
        pcg(mv, torch.ones(1, 4), x0=torch.ones(1, 5))
    with pytest.raises(ShapeError):
        pcg(mv, torch.ones(1, 4), precond=torch.ones(1, 3))
    bad = torch.ones(1, 4)
    bad[0, 1] = float("nan")
    with pytest.raises(ImageError, match="NaN"):
        pcg(mv, bad)
    res = pcg(mv, torch.zeros(1, 4, dtype=torch.float64))
    assert res.converged and res.iterations == 0


def test_callable_preconditioner_and_image_shaped_input():
    torch.manual_seed(0)
    w = torch.rand(2, 1, 5, 6, dtype=torch.float64) + 0.5

    def mv(x):  # diag(w) + a 1-D Laplacian along x: SPD
        lap = 2 * x
        lap[..., 1:] -= x[..., :-1]
        lap[..., :-1] -= x[..., 1:]
        return w * x + lap

    b = torch.randn(2, 1, 5, 6, dtype=torch.float64)
    res = pcg(mv, b, precond=lambda r: r / (w + 2), tol=1e-10)
    torch.testing.assert_close(mv(res.x), b, atol=1e-8, rtol=0)


def test_skipping_the_final_true_residual_keeps_the_iterates():
    mats = [_spd(30, s, cond=1e3) for s in range(2)]
    b = torch.randn(2, 30, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    pre = torch.stack([1 / m.diagonal() for m in mats])
    full = pcg(_batch_matvec(mats), b, precond=pre, tol=1e-12, max_iter=7, warn=False)
    fast = pcg(
        _batch_matvec(mats), b, precond=pre, tol=1e-12, max_iter=7, warn=False, true_residual=False
    )
    assert torch.equal(full.x, fast.x) and full.iterations == fast.iterations == 7
    # in float64 the recursive residual equals the true one to rounding
    torch.testing.assert_close(fast.residual, full.residual, rtol=1e-6, atol=1e-12)


def test_channels_last_input_gives_the_same_answer():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(2, 3, 6, 5, generator=g, dtype=torch.float64) + 0.5
    b = torch.randn(2, 3, 6, 5, generator=g, dtype=torch.float64)

    def mv(x):
        return w * x + 0.1 * x.roll(1, dims=-1) + 0.1 * x.roll(-1, dims=-1)

    ref = pcg(mv, b, x0=torch.zeros_like(b), tol=1e-10)
    cl = b.to(memory_format=torch.channels_last)
    res = pcg(mv, cl, x0=torch.zeros_like(cl), tol=1e-10)
    torch.testing.assert_close(res.x, ref.x)
    assert res.x.is_contiguous()
    torch.testing.assert_close(w * ref.x + 0.1 * ref.x.roll(1, -1) + 0.1 * ref.x.roll(-1, -1), b)


def test_known_start_residual_saves_a_product_and_gives_the_same_iterates():
    """``r0`` (the residual at ``x0``) replaces the first product; a second solve started
    from the first one's ``PCGResult.r`` corrected by the change of the right-hand side
    matches a solve that computes its residual."""
    mats = [_spd(20, s) for s in range(2)]
    g = torch.Generator().manual_seed(7)
    b1 = torch.randn(2, 20, generator=g, dtype=torch.float64)
    b2 = b1 + 0.1 * torch.randn(2, 20, generator=g, dtype=torch.float64)
    calls = []

    def counted(x):
        calls.append(1)
        return _batch_matvec(mats)(x)

    first = pcg(counted, b1, max_iter=3, warn=False, true_residual=False)
    torch.testing.assert_close(first.r, b1 - _batch_matvec(mats)(first.x))
    calls.clear()
    fresh = pcg(counted, b2, x0=first.x, max_iter=4, warn=False, true_residual=False)
    n_fresh = len(calls)
    calls.clear()
    reused = pcg(
        counted, b2, x0=first.x, max_iter=4, warn=False, true_residual=False,
        r0=first.r + (b2 - b1),
    )  # fmt: skip
    assert len(calls) == n_fresh - 1
    torch.testing.assert_close(reused.x, fresh.x, rtol=1e-10, atol=1e-12)
    with pytest.raises(ShapeError, match="r0"):
        pcg(counted, b2, r0=torch.zeros(2, 19, dtype=torch.float64))


def test_pcg_callable_history_and_snapshots():
    g = torch.Generator().manual_seed(5)
    q, _ = torch.linalg.qr(torch.randn(30, 30, generator=g, dtype=torch.float64))
    a = q @ torch.diag(torch.logspace(0, 3, 30, dtype=torch.float64)) @ q.T
    b = torch.randn(1, 30, generator=g, dtype=torch.float64)
    res = pcg_callable(lambda x: x @ a, b, tol=1e-10, max_iter=200, snapshot_tols=(1e-3,))
    assert res.converged
    torch.testing.assert_close(res.x[0], torch.linalg.solve(a, b[0]), rtol=1e-8, atol=1e-8)
    assert res.history.shape == (res.iterations + 1, 1)
    assert float(res.history[0, 0]) == pytest.approx(1.0)
    k = res.iterations_to(1e-3)
    assert 0 < k <= res.iterations
    snap = res.snapshots[1e-3]
    assert float(torch.linalg.norm(b - snap @ a) / torch.linalg.norm(b)) <= 1.01e-3
    assert np.isfinite(float(res.residual))


def test_pcg_callable_runs_the_iteration_of_pcg():
    # a batch whose items stop at different iterations: the same iterates and counts as pcg,
    # and each item's recorded residual stays where it stopped
    g = torch.Generator().manual_seed(6)
    q, _ = torch.linalg.qr(torch.randn(40, 40, generator=g, dtype=torch.float64))
    a = q @ torch.diag(torch.logspace(0, 2, 40, dtype=torch.float64)) @ q.T
    b = torch.randn(2, 40, generator=g, dtype=torch.float64)
    b[1] = q[:, 0] + 1e-3 * b[1]  # nearly an eigenvector: converges in a few iterations
    diag = (1 / a.diagonal()).expand(2, 40)
    res = pcg_callable(lambda x: x @ a, b, precond=diag, tol=1e-9, max_iter=100)
    ref = pcg(lambda x: x @ a, b, precond=diag, tol=1e-9, max_iter=100)
    assert torch.equal(res.x, ref.x) and torch.equal(res.item_iterations, ref.item_iterations)
    stop = int(res.item_iterations[1])
    assert stop < res.iterations and bool((res.history[stop:, 1] == res.history[stop, 1]).all())
