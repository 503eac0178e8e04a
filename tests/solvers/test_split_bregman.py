import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.priors.reflectance_terms import PairL1Term, StencilL1Term
from torchiid.priors.stencil import Stencil
from torchiid.solvers.split_bregman import SplitBregmanOptions, split_bregman

D = torch.float64


def solve(rho, terms, gammas, gamma_a=1.0, z0=None, **options):
    """split_bregman with its settings as keywords (gathered into SplitBregmanOptions)."""
    o = SplitBregmanOptions(**options)
    return split_bregman(rho, terms, gammas, gamma_a=gamma_a, z0=z0, options=o)


TIGHT = dict(max_outer=2000, tol=1e-12, cg_tol=1e-13, cg_max_iter=100)


def _objective(z, rho, mats, gammas, gamma_a):
    """Independent dense evaluation of γ_a‖z − ρ‖² + Σ γ_k ‖M_k z‖₁ (single image)."""
    zc = z[0].reshape(z.shape[1], -1).T
    obj = gamma_a * (z - rho).square().sum()
    for m, g in zip(mats, gammas, strict=True):
        obj = obj + g * (m @ zc).abs().sum()
    return obj


def test_matches_brute_force_grid_1d():
    # 3 pixels in a row, one channel: exhaustive search on a 0.005 grid
    rho = torch.tensor([0.1, 0.6, 0.45], dtype=D).view(1, 1, 1, 3)
    i, j = torch.tensor([[0, 1, 0]]), torch.tensor([[1, 2, 2]])
    w = torch.tensor([[1.0, 0.8, 0.3]], dtype=D)
    term = PairL1Term(i, j, w, 1, 3)
    res = solve(rho, [term], [0.1], gamma_a=1.0, theta=1.0, **TIGHT)
    grid = torch.arange(0.0, 0.8001, 0.005, dtype=D)
    z = torch.stack(torch.meshgrid(grid, grid, grid, indexing="ij"), -1).reshape(-1, 3)
    r = rho.reshape(3)
    obj = (z - r).square().sum(1) + 0.1 * (
        (z[:, 0] - z[:, 1]).abs()
        + 0.8 * (z[:, 1] - z[:, 2]).abs()
        + 0.3 * (z[:, 0] - z[:, 2]).abs()
    )
    best = z[obj.argmin()]
    sb_obj = _objective(res.z, rho, [term.matrix().to_dense()], [0.1], 1.0)
    assert float(sb_obj) <= float(obj.min()) + 1e-9
    torch.testing.assert_close(res.z.reshape(3), best, atol=6e-3, rtol=0)


def test_matches_primal_dual_reference_4x4():
    g = torch.Generator().manual_seed(0)
    h = w = 4
    st = Stencil.square(h, w, 3)
    rho = torch.rand(1, 2, h, w, generator=g, dtype=D)
    a = StencilL1Term(st, torch.rand(1, 4, h, w, generator=g, dtype=D))
    c = PairL1Term(
        torch.tensor([[0, 3, 5]]),
        torch.tensor([[15, 12, 10]]),
        torch.tensor([[0.7, 0.3, 1.0]], dtype=D),
        h,
        w,
    )
    gam = [0.3, 0.2]
    res = solve(rho, [a, c], gam, gamma_a=1.0, theta=10.0, **TIGHT)
    # Chambolle-Pock primal-dual on dense matrices, float64
    mats = [a.matrix().to_dense(), c.matrix().to_dense()]
    k = torch.cat(mats)
    lim = torch.cat(
        [torch.full((m.shape[0], 1), gg, dtype=D) for m, gg in zip(mats, gam, strict=True)]
    )
    # (in numpy: 20000 tiny torch ops cost minutes on a loaded 2-core machine)
    kn, limn = k.numpy(), lim.numpy()
    r = rho[0].reshape(2, -1).T.numpy()
    step = 0.99 / float(torch.linalg.matrix_norm(k, 2))
    x, xb, y = r.copy(), r.copy(), np.zeros((kn.shape[0], 2))
    for _ in range(20000):
        y = np.clip(y + step * (kn @ xb), -limn, limn)
        xn = (x - step * (kn.T @ y) + 2 * step * r) / (1 + 2 * step)
        xb, x = 2 * xn - x, xn
    x = torch.from_numpy(x)
    zc = res.z[0].reshape(2, -1).T
    torch.testing.assert_close(zc, x, atol=1e-4, rtol=0)
    ref_obj = _objective(x.T.reshape(1, 2, h, w), rho, mats, gam, 1.0)
    sb_obj = _objective(res.z, rho, mats, gam, 1.0)
    assert abs(float(sb_obj - ref_obj)) < 1e-6
    # the reported objective is the true one, ends at the optimum and never goes below it
    torch.testing.assert_close(res.objective[-1, 0], sb_obj)
    assert float(res.objective[-1, 0]) < float(res.objective[0, 0])
    assert float(res.objective.min()) >= float(ref_obj) - 1e-9
    assert bool(res.converged.all())


def _problem(b=2, h=12, w=13, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    st = Stencil.square(h, w, 5)
    rho = torch.rand(b, 3, h, w, generator=g).to(dtype)
    term = StencilL1Term(st, torch.rand(b, st.num_offsets, h, w, generator=g).to(dtype))
    return rho, term


def test_objective_decreases_overall():
    rho, term = _problem(b=1, dtype=D)
    res = solve(rho, [term], [0.05], gamma_a=1.0, theta=1.0, max_outer=30, tol=0, cg_max_iter=20)
    obj = res.objective[:, 0]
    assert obj.shape[0] == 31
    assert float(obj[-1]) < 0.8 * float(obj[0])
    # late iterations are monotone for this problem (Split-Bregman is not monotone in general)
    assert bool((obj[10:].diff() <= 1e-9).all())


def test_untracked_objective_gives_the_same_solution():
    rho, term = _problem(b=2, dtype=D)
    kw = dict(gamma_a=1.0, theta=2.0, max_outer=5, tol=0, cg_max_iter=7)
    tracked = solve(rho, [term], [0.05], **kw)
    fast = solve(rho, [term], [0.05], track_objective=False, **kw)
    assert fast.objective is None and tracked.objective.shape == (6, 2)
    torch.testing.assert_close(fast.z, tracked.z)
    assert fast.outer_iterations.tolist() == tracked.outer_iterations.tolist()


def test_batch_equals_one_by_one_and_per_image_stopping():
    rho, term = _problem(b=2)
    rho[1] = 0.5  # constant image: z = rho is optimal, stops after one iteration
    kw = dict(gamma_a=1.0, theta=2.0, max_outer=6, tol=1e-4, cg_max_iter=7)
    res = solve(rho, [term], [0.05], **kw)
    assert res.outer_iterations.tolist() == [6, 1]
    for bi in range(2):
        one = StencilL1Term(term.stencil, term.weights[bi : bi + 1])
        r1 = solve(rho[bi : bi + 1], [one], [0.05], **kw)
        torch.testing.assert_close(res.z[bi : bi + 1], r1.z, atol=1e-5, rtol=1e-5)
        assert int(r1.outer_iterations[0]) == int(res.outer_iterations[bi])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_and_no_terms(dtype):
    rho, term = _problem(b=1, dtype=dtype)
    res = solve(rho, [term], [0.05], max_outer=2)
    assert res.z.dtype == dtype and res.z.shape == rho.shape
    res0 = solve(rho, [term], [0.0])
    assert torch.equal(res0.z, rho) and res0.cg_iterations == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    rho, term = _problem(b=1, dtype=D)
    cpu = solve(rho, [term], [0.05], max_outer=3)
    gterm = StencilL1Term(Stencil.square(12, 13, 5, device="cuda"), term.weights.cuda())
    gpu = solve(rho.cuda(), [gterm], [0.05], max_outer=3)
    torch.testing.assert_close(gpu.z.cpu(), cpu.z)


def test_errors():
    rho, term = _problem(b=1)
    with pytest.raises(ParameterError, match="got 1 terms but 2 weights"):
        solve(rho, [term], [1.0, 2.0])
    with pytest.raises(ParameterError, match="gamma_a and theta must be > 0"):
        solve(rho, [term], [1.0], gamma_a=0.0)
    with pytest.raises(ParameterError, match=">= 0"):
        solve(rho, [term], [-1.0])
    with pytest.raises(ShapeError, match=r"z0 has shape \(1, 3, 4, 4\)"):
        solve(rho, [term], [1.0], z0=torch.zeros(1, 3, 4, 4))
    bad = rho.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ImageError, match="rho contains 1 NaN"):
        solve(bad, [term], [1.0])
    with pytest.raises(ShapeError, match=r"expected rho of shape \(B, C, H, W\)"):
        solve(rho[0], [term], [1.0])


def test_the_settings_are_no_keywords_of_the_solver():
    # SplitBregmanOptions holds them
    rho, term = _problem(b=1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'theta'"):
        split_bregman(rho, [term], [0.05], theta=2.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'max_outer'"):
        split_bregman(rho, [term], [0.05], options=SplitBregmanOptions(theta=2.0), max_outer=3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("max_outer", [1, 2, 3, 6])
def test_unstored_and_replayed_states_give_the_stored_state_iterates(dtype, max_outer):
    """``keep_state=False`` (the pipeline's setting without a warm start): the last update's
    state is not written, and on CPU the state is replayed from the past ``z`` instead of
    stored (up to ``REPLAY_STEPS`` updates, then stored). The iterates are the stored-state
    solver's, to round-off; each ``z`` step after the first starts from the carried
    residual in both runs."""
    from torchiid.priors import kernels
    from torchiid.priors import reflectance_terms as rt

    rho, term = _problem(b=2, h=23, w=19, dtype=dtype)
    kw = dict(gamma_a=1.0, theta=2.0, max_outer=max_outer, tol=0, cg_max_iter=4)
    stored = solve(rho, [term], [0.05], track_objective=False, **kw)
    assert term.state_written
    lean = StencilL1Term(term.stencil, term.weights, keep_state=False)
    calls = []
    real = kernels.bregman_replay
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(kernels, "bregman_replay", lambda h, *a: calls.append(len(h)) or real(h, *a))
        res = solve(rho, [lean], [0.05], track_objective=False, **kw)
    tol = 2e-5 if dtype == torch.float32 else 1e-11
    torch.testing.assert_close(res.z, stored.z, rtol=tol, atol=tol)
    if kernels._numba() is not None:
        # updates at z_0 .. z_{max_outer - 1}: replayed while their history is short enough
        assert calls == [m for m in range(max_outer) if m <= rt.REPLAY_STEPS]
    assert not lean.state_written  # the last update is never stored


def test_a_term_told_not_to_replay_stores_its_state():
    # the reflectance stage sets replay=False for solves longer than REPLAY_STEPS + 1
    # updates: no replay at all, the stored-state iterates
    from torchiid.priors import kernels

    rho, term = _problem(b=1, h=15, w=17)
    kw = dict(gamma_a=1.0, theta=2.0, max_outer=6, tol=0, cg_max_iter=4)
    stored = solve(rho, [term], [0.05], track_objective=False, **kw)
    lean = StencilL1Term(term.stencil, term.weights, keep_state=False, replay=False)
    calls = []
    real = kernels.bregman_replay
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(kernels, "bregman_replay", lambda h, *a: calls.append(len(h)) or real(h, *a))
        res = solve(rho, [lean], [0.05], track_objective=False, **kw)
    assert calls == []
    torch.testing.assert_close(res.z, stored.z, rtol=2e-5, atol=2e-5)


def _gap_problem(seed=3, h=14, w=15, dtype=D, state=None):
    g = torch.Generator().manual_seed(seed)
    st = Stencil.square(h, w, 5)
    rho = torch.rand(1, 3, h, w, generator=g).to(dtype)
    local = StencilL1Term(
        st, torch.rand(1, st.num_offsets, h, w, generator=g).to(dtype), state=state
    )
    n = 40
    i = torch.randint(0, h * w, (1, n), generator=g)
    j = torch.randint(0, h * w, (1, n), generator=g)
    pairs = PairL1Term(i, j, torch.rand(1, n, generator=g).to(dtype), h, w)
    return rho, [local, pairs], [0.05, 0.03]


def _excess(res, rho, terms, gammas, j_star):
    mats = [t.matrix().to_dense().to(rho.dtype) for t in terms]
    j = float(_objective(res.z.to(rho.dtype), rho, mats, gammas, 1.0))
    return (j - j_star) / j


def test_duality_gap_bounds_the_excess_and_stops_the_solve():
    rho, terms, gam = _gap_problem()
    mats = [t.matrix().to_dense() for t in terms]
    ref = solve(rho, terms, gam, gamma_a=1.0, theta=1.0, **{**TIGHT, "max_outer": 600})
    j_star = float(_objective(ref.z, rho, mats, gam, 1.0))
    kw = dict(gamma_a=1.0, theta=1.0, max_outer=3000, cg_tol=1e-10, cg_max_iter=100)
    iterations = []
    for tol in (1e-1, 1e-2, 1e-3):
        res = solve(rho, terms, gam, gap_tol=tol, check_every=1, **kw)
        excess = _excess(res, rho, terms, gam, j_star)
        gap = float(res.gap[0])
        assert bool(res.converged.all()) and gap < tol
        # the gap is an upper bound of the relative excess over the minimum, not a loose one
        assert -1e-12 <= excess <= gap
        iterations.append(int(res.outer_iterations[0]))
    assert iterations == sorted(iterations) and iterations[0] < iterations[-1]


@pytest.mark.parametrize("fixed", [False, True], ids=["float64", "int16"])
def test_residual_balancing_lowers_a_too_large_penalty(fixed):
    dtype = torch.float32 if fixed else D
    kw = dict(gamma_a=1.0, gap_tol=1e-3, max_outer=3000, cg_tol=1e-8, cg_max_iter=20)
    theta = 40.0
    rho, terms, gam = _gap_problem(dtype=dtype)
    # the minimum, certified by the gap (which the test above checks against TIGHT)
    exact = _gap_problem()[1]
    mats = [t.matrix().to_dense() for t in exact]
    ref = solve(
        rho.double(), exact, gam, gamma_a=1.0, theta=1.0, gap_tol=1e-6, check_every=1,
        max_outer=3000, cg_tol=1e-12, cg_max_iter=100,
    )  # fmt: skip
    assert bool(ref.converged.all())
    j_star = float(_objective(ref.z, rho.double(), mats, gam, 1.0))
    plain = solve(rho, terms, gam, theta=theta, **kw)
    storage = torch.empty(1, 3, terms[0].stencil.num_offsets, 14, 15, dtype=torch.int16)
    rho, terms, gam = _gap_problem(dtype=dtype, state=storage if fixed else None)
    balanced = solve(rho, terms, gam, theta=theta, theta_range=(theta / 64, theta), **kw)
    assert bool(plain.converged.all()) and bool(balanced.converged.all())
    assert theta / 64 <= balanced.theta < theta
    # (measured: 45 iterations against 515)
    assert int(balanced.outer_iterations[0]) < int(plain.outer_iterations[0]) / 2
    # the multipliers survive the changes of θ: the same minimiser, within the gap
    excess = _excess(balanced, rho.double(), terms, gam, j_star)
    assert -2e-6 <= excess <= float(balanced.gap[0]) + 1e-6


def test_gap_rule_falls_back_to_the_change_without_measuring_terms():
    rho, terms, gam = _gap_problem()

    class Opaque:  # a term that cannot measure its updates
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            if name == "bregman_stats":
                raise AttributeError(name)
            return getattr(self.inner, name)

    kw = dict(gamma_a=1.0, theta=1.0, max_outer=500, tol=1e-4, cg_max_iter=30)
    res = solve(rho, [Opaque(terms[0]), terms[1]], gam, gap_tol=1e-3, **kw)
    ref = solve(rho, terms, gam, **kw)
    assert bool(res.gap.isnan().all()) and bool(res.converged.all())
    torch.testing.assert_close(res.z, ref.z)
    assert res.outer_iterations.tolist() == ref.outer_iterations.tolist()
    # a solve shorter than check_every still measures its gap, at its last update
    short = solve(rho, terms, gam, gap_tol=1e-3, max_outer=2, gamma_a=1.0, theta=1.0)
    assert bool(short.gap.isfinite().all()) and not bool(short.converged.any())
    with pytest.raises(ParameterError, match="balance"):
        solve(rho, terms, gam, gap_tol=1e-3, balance=(1.0, 10.0))
    with pytest.raises(ParameterError, match="gap_tol"):
        solve(rho, terms, gam, gap_tol=0.0)
    with pytest.raises(ParameterError, match="theta_range"):
        solve(rho, terms, gam, theta=1.0, gap_tol=1e-3, theta_range=(2.0, 4.0))


@pytest.mark.parametrize("scale", [1.0, 10.0])
def test_certified_distance_bounds_the_distance_to_the_minimiser(scale):
    # J is 2γ_a-strongly convex: γ_a‖z − z*‖² <= J(z) − J* <= J(z) − D(p), so the reported
    # distance bounds ‖z − z*‖ / ‖ρ‖ (a wrong γ_a or a missing square root breaks it; the
    # scaled ρ, whose J(z) is far from ‖ρ‖², catches a relative gap in place of J(z) − D(p))
    rho, terms, gam = _gap_problem()
    rho = rho * scale
    gam = [4 * g for g in gam]
    kw = dict(gamma_a=4.0, theta=4.0, max_outer=5000, cg_tol=1e-10, cg_max_iter=100)
    ref = solve(rho, terms, gam, gap_tol=1e-7, check_every=1, **kw)
    d_ref = float(ref.distance[0])
    assert d_ref < 1e-3
    norm = float(rho.norm())
    for tol in (1e-1, 1e-2, 1e-3):
        res = solve(rho, terms, gam, gap_tol=tol, check_every=1, **kw)
        true = float((res.z - ref.z).norm()) / norm
        bound = float(res.distance[0])
        assert true <= bound + d_ref
        if tol == 1e-1:
            # and not a loose one here (measured: 0.141 against 0.124)
            assert bound <= 1.5 * true


def test_adaptive_measurements_stop_near_the_first_iteration_below_the_tolerance():
    # measuring the gap at every iteration finds the first one below the tolerance; the
    # extrapolated schedule (at most every 5) must stop there or one after (a fixed interval
    # of 5 stops at 20 for 1e-3, and fails), with fewer measurements than half the iterations
    rho, terms, gam = _gap_problem()
    kw = dict(gamma_a=1.0, theta=1.0, max_outer=3000, cg_tol=1e-10, cg_max_iter=100)
    measured = []
    real = StencilL1Term.bregman_step

    def counting(self, *a, stats=False, **k):
        measured.append(stats)
        return real(self, *a, stats=stats, **k)

    for tol in (1e-2, 1e-3):
        every = solve(rho, terms, gam, gap_tol=tol, check_every=1, **kw)
        first = int(every.outer_iterations[0])
        measured.clear()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(StencilL1Term, "bregman_step", counting)
            res = solve(rho, terms, gam, gap_tol=tol, check_every=5, **kw)
        n = int(res.outer_iterations[0])
        assert bool(res.converged.all()) and float(res.gap[0]) < tol
        assert first <= n <= first + 1, (first, n)
        # (measured: every iteration stops at 9 and 18, this schedule at 10 and 18 after 2 and 5
        # measurements; a fixed interval of 5 stops at the next multiple of 5, 10 and 20)
        assert sum(measured) < n / 2
