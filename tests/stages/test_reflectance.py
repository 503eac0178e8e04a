import itertools
import math
import weakref

import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.params import Parameters, ReflectanceParameters
from torchiid.priors.reflectance_terms import COLOUR_WEIGHTS, lab_features, stencil_affinity
from torchiid.priors.representatives import global_pair_term, representative_pixels
from torchiid.priors.stencil import Stencil
from torchiid.stages.config import ReflectanceProblem
from torchiid.stages.reflectance import (
    ReflectanceCache,
    build_reflectance_terms,
    shading_from_ratio,
    solve_reflectance,
)
from torchiid.synthetic import mondrian


def _scene(batch=1, h=48, w=64, seed=3, noise=0.03):
    s = mondrian(h, w, batch=batch, patches=8, seed=seed)
    g = torch.Generator().manual_seed(0)
    rho = (s.reflectance + noise * torch.randn(s.reflectance.shape, generator=g)).clamp(0, 1)
    codes = torch.randn(int(s.labels.max()) + 1, 4, generator=g) * 0.02
    gpca = codes[s.labels].permute(0, 3, 1, 2).contiguous()
    return s, rho, gpca


#: the paper's gammas (20, 20, 2) and gamma_a = 1; 3 Bregman iterations of 5 CG steps
W = ReflectanceParameters(bregman_iter=3, bregman_cg_iter=5)


def _rmse(a, b):
    return float((a - b).square().mean().sqrt())


def test_mondrian_l1_solution_is_closer_to_truth_than_rho():
    s, rho, gpca = _scene()
    r = solve_reflectance(ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels), W)
    before, after = _rmse(rho, s.reflectance), _rmse(r.reflectance, s.reflectance)
    # measured: 0.030 -> 0.012 with the defaults (0.021 with colour_weights="wide")
    assert after < 0.8 * before
    assert r.reflectance.shape == (1, 3, 48, 64) and r.shading.shape == (1, 1, 48, 64)
    # the gray shading S = Σ_c I_c / Σ_c R_c is the true one up to a scale, steadier than ρ's
    # (measured: spread of S / S_true 1.4%, of the same ratio with ρ 4.2%)
    expected = s.image.sum(1, keepdim=True) / r.reflectance.sum(1, keepdim=True)
    torch.testing.assert_close(r.shading, expected)

    def spread(x):
        return float(x.std() / x.mean())

    with_rho = s.image.sum(1, keepdim=True) / rho.sum(1, keepdim=True)
    assert spread(r.shading / s.shading) < 0.5 * spread(with_rho / s.shading)
    assert int(r.num_representatives[0]) == int(torch.unique(s.labels).numel())
    assert float(r.solver.objective[-1, 0]) < float(r.solver.objective[0, 0])


def test_shading_from_ratio_by_hand():
    image = torch.tensor([[0.2, 0.2], [0.4, 0.4], [0.6, 0.6]]).view(1, 3, 1, 2)
    refl = torch.tensor([[0.1, 0.0], [0.2, 0.0], [0.3, 0.0]]).view(1, 3, 1, 2)
    got = shading_from_ratio(image, refl)  # 1.2 / 0.6, and 1.2 over the floor 1e-4
    torch.testing.assert_close(got, torch.tensor([2.0, 12000.0]).view(1, 1, 1, 2))
    assert float(shading_from_ratio(image, refl, eps=0.5)[0, 0, 0, 1]) == pytest.approx(2.4)


def test_cache_reuses_the_proposal_factor_and_changes_nothing():
    s, rho, gpca = _scene(h=32, w=40)
    opts = W.replace(bregman_iter=2, bregman_cg_iter=3, window=5)
    problem = ReflectanceProblem(rho, s.image, gpca=gpca)
    scaled = problem.replace(rho=0.9 * rho)  # new rho, same g̊
    cache = ReflectanceCache()
    first = solve_reflectance(problem, opts, cache=cache)
    again = solve_reflectance(scaled, opts, cache=cache)
    assert cache.hits == 1
    torch.testing.assert_close(again.reflectance, solve_reflectance(scaled, opts).reflectance)
    torch.testing.assert_close(first.reflectance, solve_reflectance(problem, opts).reflectance)
    gpca.mul_(2.0)  # modified in place: the factor is recomputed, not reused
    solve_reflectance(problem, opts, cache=cache)
    assert cache.hits == 1
    # the merged A/B weights of both builds live in one storage, written again in place
    built = [build_reflectance_terms(p, opts, cache=cache) for p in (problem, scaled)]
    ptrs = {b.terms["A+B"][1].weights.data_ptr() for b in built}
    assert len(ptrs) == 1 and ptrs == {cache.weights_buffer(rho, 12).data_ptr()}


def test_the_last_solve_writes_its_weights_over_the_proposal_factor():
    s, rho, gpca = _scene(h=32, w=40)
    opts = W.replace(bregman_iter=2, bregman_cg_iter=3, window=5)
    problem = ReflectanceProblem(rho, s.image, gpca=gpca)
    scaled = problem.replace(rho=0.9 * rho)
    cache = ReflectanceCache()
    solve_reflectance(problem, opts, cache=cache)
    factor = cache.semantic[1]
    earlier_weights = weakref.ref(cache.weights_buffer(rho, 12))
    kept_cache = ReflectanceCache()
    solve_reflectance(problem, opts, cache=kept_cache)
    want = build_reflectance_terms(scaled, opts, cache=kept_cache).terms["A+B"][1].weights
    cache.last = True
    built = build_reflectance_terms(scaled, opts, cache=cache)
    weights = built.terms["A+B"][1].weights
    # one (B, K, H, W) tensor: the factor's storage now holds the weights, the same values
    assert weights.data_ptr() == factor.data_ptr() and torch.equal(weights, want)
    assert cache.hits == 1 and cache.semantic is None  # reused, then let go
    del built, weights, factor
    assert earlier_weights() is None  # the weights' storage of the earlier solve is let go
    # the solve is the same as with a kept factor (a cache's storage: its 16-bit Bregman
    # variable)
    last_cache = ReflectanceCache()
    solve_reflectance(problem, opts, cache=last_cache)
    last_cache.last = True
    last = solve_reflectance(scaled, opts, cache=last_cache)
    same = solve_reflectance(scaled, opts, cache=kept_cache)
    assert torch.equal(last.reflectance, same.reflectance)
    # a last solve on a new cache makes the factor and keeps nothing
    fresh = ReflectanceCache(last=True)
    got = solve_reflectance(problem, opts, cache=fresh)
    assert fresh.semantic is None and fresh.hits == 0
    assert torch.equal(
        got.reflectance, solve_reflectance(problem, opts, cache=ReflectanceCache()).reflectance
    )


def test_without_a_cache_the_weights_are_written_over_their_own_factor(monkeypatch):
    import torchiid.stages.reflectance_system as rs

    s, rho, gpca = _scene(h=32, w=40)
    opts = W.replace(bregman_iter=2, bregman_cg_iter=3, window=5)
    problem = ReflectanceProblem(rho, s.image, gpca=gpca)
    want = build_reflectance_terms(problem, opts, cache=ReflectanceCache())
    over = []
    merged = rs.merged_stencil_affinity

    def recording(colour, factor, *args, out=None, **kwargs):
        over.append(out is factor)
        return merged(colour, factor, *args, out=out, **kwargs)

    monkeypatch.setattr(rs, "merged_stencil_affinity", recording)
    got = build_reflectance_terms(problem, opts)
    assert over == [True]
    assert torch.equal(got.terms["A+B"][1].weights, want.terms["A+B"][1].weights)


def test_cache_reuses_the_segment_layout_and_changes_nothing():
    s, rho, gpca = _scene(h=32, w=40)
    opts = W.replace(bregman_iter=2, bregman_cg_iter=3, window=5)
    mask = torch.ones(1, 1, 32, 40, dtype=torch.bool)
    mask[..., :3, :] = False
    problem = ReflectanceProblem(rho, s.image, segments=s.labels, mask=mask)
    cache = ReflectanceCache()
    for scale in (1.0, 0.8, 1.3):  # a new rho per alternation, the same segments and mask
        p = problem.replace(rho=scale * rho)
        got = solve_reflectance(p, opts, cache=cache)
        ref = solve_reflectance(p, opts)
        assert torch.equal(got.reflectance, ref.reflectance)
        assert torch.equal(got.num_representatives, ref.num_representatives)
    assert cache.hits == 2
    solve_reflectance(problem.replace(mask=~mask), opts, cache=cache)  # another mask
    assert cache.hits == 2


def test_batch_equals_one_by_one():
    s, rho, gpca = _scene(batch=2, h=32, w=40)
    opts = W.replace(bregman_iter=3, bregman_cg_iter=4, window=5)
    r = solve_reflectance(ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels), opts)
    for b in range(2):
        sl = slice(b, b + 1)
        one = ReflectanceProblem(rho[sl], s.image[sl], gpca=gpca[sl], segments=s.labels[sl])
        r1 = solve_reflectance(one, opts)
        torch.testing.assert_close(r.reflectance[sl], r1.reflectance, atol=1e-5, rtol=1e-5)


def test_mask_keeps_rho_outside():
    s, rho, gpca = _scene(h=24, w=32)
    mask = torch.ones(1, 1, 24, 32, dtype=torch.bool)
    mask[..., :8, :10] = False
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels, mask=mask)
    r = solve_reflectance(problem, W.replace(window=5))
    assert torch.equal(r.reflectance[~mask.expand_as(rho)], rho[~mask.expand_as(rho)])
    assert not torch.equal(r.reflectance[mask.expand_as(rho)], rho[mask.expand_as(rho)])


def test_terms_switch_off():
    s, rho, gpca = _scene(h=20, w=24)
    # the old gamma_m=None (off) is 0 now
    off_w = W.replace(gamma_l=0, gamma_m=0, gamma_g=0)
    off = solve_reflectance(ReflectanceProblem(rho, s.image, gpca=gpca), off_w)
    torch.testing.assert_close(off.reflectance, rho)
    switched = solve_reflectance(
        ReflectanceProblem(rho, s.image, gpca=gpca),
        W.replace(use_rl=False, use_rm=False, use_rg=False),
    )
    torch.testing.assert_close(switched.reflectance, rho)
    opts = W.replace(window=5)
    a = solve_reflectance(ReflectanceProblem(rho, s.image), opts.replace(gamma_m=0, gamma_g=0))
    a_nogpca = solve_reflectance(
        ReflectanceProblem(rho, s.image, gpca=None), opts.replace(use_rg=False)
    )
    torch.testing.assert_close(a.reflectance, a_nogpca.reflectance)
    assert int(a.num_representatives[0]) == 0


def test_merged_and_separate_objectives_are_identical():
    # merging A and B is an exact reformulation: same objective at every z
    s, rho, gpca = _scene(h=12, w=14, noise=0.05)
    rho, img, gp = rho.double(), s.image.double(), gpca.double()
    g = torch.Generator().manual_seed(7)
    z0 = (rho + 0.05 * torch.randn(rho.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    problem = ReflectanceProblem(rho, img, gpca=gp, segments=s.labels)
    opts = W.replace(window=5, bregman_iter=1, value_scale=1.0)  # the objective at z0 is row 0
    m = solve_reflectance(problem, opts, z0=z0, merge=True)
    sep = solve_reflectance(problem, opts, z0=z0, merge=False)
    # independent objective: γ_l‖v^l Mz‖₁ + γ_m‖v^m Mz‖₁ + γ_g‖v^g C z‖₁ + γ_a‖z − ρ‖²
    w_l, lab_scale = COLOUR_WEIGHTS["bi"]  # the default colour_weights
    rbar = lab_features(rho, luminance_weight=w_l, lab_scale=lab_scale)
    st = Stencil.square(12, 14, 5)
    vl = stencil_affinity(rbar, st, 0.05)
    vm = vl * stencil_affinity(gp, st, 0.05)
    c = global_pair_term(rbar, representative_pixels(rbar, s.labels), 0.05)
    d = st.apply(z0).abs()
    ref = float(
        20 * (vl[:, None] * d).sum()
        + 20 * (vm[:, None] * d).sum()
        + 2 * c.l1(z0).sum()
        + (z0 - rho).square().sum()
    )
    assert abs(float(m.solver.objective[0, 0]) - ref) < 1e-9 * ref
    assert abs(float(sep.solver.objective[0, 0]) - ref) < 1e-9 * ref


def test_errors():
    s, rho, gpca = _scene(h=16, w=16)
    P = ReflectanceProblem
    with pytest.raises(ShapeError, match="batch size and \\(H, W\\) must match"):
        solve_reflectance(P(rho, s.image[..., :8]), W)
    bad = rho.clone()
    bad[0, 1, 2, 3] = float("nan")
    with pytest.raises(ImageError, match="rho contains 1 NaN"):
        solve_reflectance(P(bad, s.image), W)
    with pytest.raises(ShapeError, match=r"expected gpca of shape \(1, d, 16, 16\)"):
        solve_reflectance(P(rho, s.image, gpca=gpca[..., :8]), W)
    with pytest.raises(ShapeError, match="expected a bool mask"):
        solve_reflectance(P(rho, s.image, mask=torch.ones(1, 1, 16, 16)), W)
    with pytest.raises(ShapeError, match=r"expected segments of shape \(1, 16, 16\)"):
        solve_reflectance(P(rho, s.image, segments=s.labels[:, :4]), W)
    with pytest.raises(ParameterError, match="takes a torchiid.params.ReflectanceParameters"):
        solve_reflectance(P(rho, s.image), Parameters())
    # the parameters are checked where they are made
    with pytest.raises(ParameterError, match="colour_weights must be one of bi, wide"):
        W.replace(colour_weights="narrow")
    with pytest.raises(ParameterError, match=r"gamma_l must be >= 0"):
        W.replace(gamma_l=-1.0)
    with pytest.raises(ParameterError, match=r"parameter t must be > 0"):
        W.replace(t=0.0)


def test_channels_last_inputs_give_the_same_answer():
    s, rho, gpca = _scene(h=24, w=32)
    opts = W.replace(bregman_iter=2, bregman_cg_iter=3, window=5)
    ref = solve_reflectance(ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels), opts)
    cl = torch.channels_last
    r = solve_reflectance(
        ReflectanceProblem(
            rho.to(memory_format=cl), s.image.to(memory_format=cl), gpca=gpca, segments=s.labels
        ),
        opts,
        z0=rho.to(memory_format=cl),
    )
    torch.testing.assert_close(r.reflectance, ref.reflectance, atol=1e-6, rtol=1e-6)
    assert r.solver.z.is_contiguous()


def _tight(opts: ReflectanceParameters) -> ReflectanceParameters:
    """The same solve to a relative duality gap of 1e-3: its objective is within 0.1% of the
    minimum, certified (``J* >= ref (1 − 1e-3)``), and ``J* <= ref``."""
    return opts.replace(bregman_gap_tol=1e-3, bregman_iter=3000)


def test_converged_preset_tolerance_puts_the_objective_near_its_minimum():
    # the `converged` preset's Split-Bregman stops on a duality gap of 0.5%: Eq. 12's objective
    # ends within 0.5% of its minimum (J* <= ref: end - J* <= 0.005 end, end <= ref / 0.995)
    s, rho, gpca = _scene()
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels)
    opts = Parameters.preset("converged").reflectance  # the preset's gammas and solver
    assert opts.bregman_gap_tol == 0.005 and opts.bregman_theta_floor == 0.25
    r = solve_reflectance(problem, opts)
    assert bool(r.solver.converged.all()) and float(r.solver.gap[0]) < 0.005
    tight = solve_reflectance(problem, _tight(opts)).solver
    assert bool(tight.converged.all())
    ref = float(tight.objective[-1, 0])
    end = float(r.solver.objective[-1, 0])
    assert ref * (1 - 1e-3) <= end <= ref / 0.995
    assert end > ref * 1.0005  # a real stop, not a solve to the minimum


def test_warm_bregman_state_reaches_the_same_minimum_in_fewer_iterations():
    # a second solve on a changed rho (the next alternation: new rho, weights scaled by tau)
    # started from the first solve's Bregman variable ends at the cold start's objective
    # (within the tolerance's 2%) in fewer Bregman iterations
    s, rho, gpca = _scene()
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels)
    opts = Parameters.preset("converged").reflectance
    assert opts.bregman_warm_state  # the preset warm-starts
    # the paper's gammas (the preset's are halved: 49 vs 49 Bregman iterations here)
    opts = opts.replace(bregman_warm_state=False, gamma_l=20.0, gamma_m=20.0, gamma_g=2.0)
    warm_opts = opts.replace(bregman_warm_state=True)
    g = torch.Generator().manual_seed(5)
    rho2 = (rho * (1 + 0.05 * torch.randn(rho.shape, generator=g))).clamp(0, 1)
    nxt = problem.replace(rho=rho2)
    cache = ReflectanceCache()
    first = solve_reflectance(problem, warm_opts, cache=cache)
    assert cache.state_valid
    # kept in 16-bit fixed point, with the step of the threshold that wrote it
    assert cache._state.dtype == torch.int16 and 0 < cache.state_step < 1e-3
    warm = solve_reflectance(nxt, warm_opts.step(1.2), z0=first.reflectance, cache=cache)
    cold = solve_reflectance(nxt, opts.step(1.2), z0=first.reflectance, cache=ReflectanceCache())
    assert bool(warm.solver.converged.all()) and bool(cold.solver.converged.all())
    n_warm, n_cold = int(warm.solver.outer_iterations[0]), int(cold.solver.outer_iterations[0])
    assert n_warm < n_cold
    ref = float(solve_reflectance(nxt, _tight(opts.step(1.2))).solver.objective[-1, 0])
    for r in (warm, cold):
        assert ref * (1 - 1e-3) <= float(r.solver.objective[-1, 0]) <= ref / 0.995
    # without the option, a cache's stored state is never read
    again = solve_reflectance(nxt, opts.step(1.2), z0=first.reflectance, cache=cache)
    torch.testing.assert_close(again.reflectance, cold.reflectance)


def test_weights_too_small_for_the_fixed_point_state_keep_it_in_float32():
    # λ = γ / θ below what a 16-bit state's float32 step resolves: the cache stores the state
    # in float32 and the warm-started solve runs as before, with no error
    s, rho, gpca = _scene()
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels)
    opts = Parameters.preset("converged").reflectance.replace(gamma_a=1.0)
    tiny = opts.replace(gamma_l=1e-36, gamma_m=1e-36, gamma_g=1e-36)
    cache = ReflectanceCache()
    for _ in range(2):
        r = solve_reflectance(problem, tiny, cache=cache, track_objective=False)
        assert cache._state.dtype == torch.float32 and cache.state_valid
    # with no regularisation to speak of the answer is rho itself
    torch.testing.assert_close(r.reflectance, rho, atol=1e-5, rtol=0)
    # ordinary weights afterwards: the same cache goes back to 16 bits (and starts cold)
    paper = opts.replace(gamma_l=20.0, gamma_m=20.0, gamma_g=2.0)
    solve_reflectance(problem, paper, cache=cache, track_objective=False)
    assert cache._state.dtype == torch.int16


def test_a_solve_that_keeps_no_state_leaves_the_cache_cold():
    # without warm_state the last update's state is not written (and on CPU not stored at
    # all, replayed): the cache must not offer it to a later warm start, which then starts
    # cold, exactly as with a fresh cache
    s, rho, gpca = _scene()
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels)
    opts = Parameters.preset("default").reflectance
    assert not opts.bregman_warm_state and opts.bregman_iter == 2
    cache = ReflectanceCache()
    first = solve_reflectance(problem, opts, cache=cache, track_objective=False)
    assert not cache.state_valid
    warm_opts = opts.replace(bregman_warm_state=True)
    kw = {"z0": first.reflectance, "track_objective": False}
    a = solve_reflectance(problem, warm_opts, cache=cache, **kw)
    b = solve_reflectance(problem, warm_opts, cache=ReflectanceCache(), **kw)
    torch.testing.assert_close(a.reflectance, b.reflectance, rtol=0, atol=0)
    assert cache.state_valid  # a warm_state solve stores its last state


def test_warm_term_needs_a_state():
    st = Stencil.square(8, 8, 3)
    with pytest.raises(ParameterError, match="warm"):
        from torchiid.priors.reflectance_terms import StencilL1Term

        StencilL1Term(st, torch.ones(1, st.num_offsets, 8, 8), warm=True)


def test_a_warm_solve_starts_at_the_penalty_its_state_was_written_at(monkeypatch):
    # residual balancing lowers theta on a photo; the cache records where the state was
    # written and the next alternation's warm solve starts there (its multipliers θ b belong
    # to that θ); every solve stops on its duality gap, which the solve reports carry
    import cv2
    from skimage import data

    from torchiid.model import decompose
    from torchiid.stages import reflectance as stage

    params = Parameters.preset("converged")
    base = params.reflectance.theta * params.reflectance.value_scale
    calls = []
    real = stage.split_bregman

    def spy(*args, **kw):
        options = kw["options"]
        assert options.theta_range == (base * params.reflectance.bregman_theta_floor, base)
        res = real(*args, **kw)
        calls.append((options.theta, res.theta))
        return res

    monkeypatch.setattr(stage, "split_bregman", spy)
    small = cv2.resize(data.astronaut(), (128, 96), interpolation=cv2.INTER_AREA)
    image = (torch.from_numpy(small).permute(2, 0, 1)[None].float() / 255) ** 2.2
    out = decompose(image, params)
    assert len(calls) == params.iterations
    assert calls[0][0] == base and min(end for _, end in calls) < base
    for (_, end), (start, _) in zip(calls[:-1], calls[1:], strict=True):
        assert start == end
    reports = [r for r in out.solves if r.stage == "reflectance"]
    assert all(r.converged and r.tolerance == 0.005 and r.residual < 0.005 for r in reports)
    assert all(r.measure == "duality gap" and "duality gap" in str(r) for r in reports)
    # and a certified distance to the minimiser (tested against a reference in
    # tests/solvers/test_split_bregman.py), which the one-line report names
    assert all(0 < r.distance < 0.05 and "of the minimiser" in str(r) for r in reports)


def test_a_capped_report_does_not_certify_the_returned_reflectance():
    # a capped solve's last gap belongs to the iterate before the returned one
    from torchiid.model import SolveReport

    done = SolveReport("reflectance", 1, 45, 225, 0.0045, 0.005, 400, True, "duality gap", 0.007)
    capped = SolveReport("reflectance", 1, 400, 2000, 0.02, 0.005, 400, False, "duality gap", 0.02)
    assert "R within 0.70% of the minimiser" in str(done)
    assert "minimiser" not in str(capped) and "stopped at its cap of 400" in str(capped)


# ------------------------------------------------------------------------------------------
# An independent reference: Eq. 12 written out densely and solved by a generic solver


def _cielab(rgb):
    """CIELab (D65, 2° observer) of linear RGB in [0, 1], from the CIE formulas."""
    to_xyz = np.array(
        [
            [0.412453, 0.357580, 0.180423],
            [0.212671, 0.715160, 0.072169],
            [0.019334, 0.119193, 0.950227],
        ]
    )
    xyz = np.clip(rgb, 0, 1) @ to_xyz.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.stack(
        [116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1
    )


def _affinity(f, i, j, t):
    """``exp(−‖f_i − f_j‖² / 2t²)``, 0 below ``e^-30`` (Eq. 7)."""
    e = -float(((f[i] - f[j]) ** 2).sum()) / (2 * t * t)
    return 0.0 if e < -30 else math.exp(e)


def _dense_eq12(rho, gpca, labels, p):
    """Eq. 12's L1 rows ``w_ij (z_i − z_j)`` as a dense matrix, from the definitions alone.

    ``A`` and ``B``: every unordered pair of a ``window`` × ``window`` neighbourhood, weights
    ``γ_l v^l + γ_m v^m`` with ``v^l`` on ``r̄ = (0.5 L/100, a/36.7, b/36.7)`` (the ``"bi"``
    colour weights) and ``v^m = v^l · exp(−‖Δg̊‖²/2t²)``; ``C``: every pair of the segments'
    representatives (the pixel whose ``r̄`` is nearest the segment's mean), weight ``γ_g v^g``.
    """
    h, w, _ = rho.shape
    rbar = (_cielab(rho) * np.array([0.5 / 100, 0.05 * 120 / 220, 0.05 * 120 / 220])).reshape(-1, 3)
    g = gpca.reshape(h * w, -1)
    pixels = [(y, x) for y in range(h) for x in range(w)]
    rows = []
    for (i, a), (j, b) in itertools.combinations(enumerate(pixels), 2):
        if max(abs(a[0] - b[0]), abs(a[1] - b[1])) <= p.window // 2:
            v_l = _affinity(rbar, i, j, p.t)
            rows.append((i, j, p.gamma_l * v_l + p.gamma_m * v_l * _affinity(g, i, j, p.t)))
    flat = labels.reshape(-1)
    reps = []
    for s in np.unique(flat):
        members = np.flatnonzero(flat == s)
        mean = rbar[members].mean(0)
        reps.append(min(members, key=lambda k: float(((rbar[k] - mean) ** 2).sum())))
    for i, j in itertools.combinations(reps, 2):
        rows.append((i, j, p.gamma_g * _affinity(rbar, i, j, p.t)))
    m = np.zeros((len(rows), h * w))
    for k, (i, j, weight) in enumerate(rows):
        m[k, i], m[k, j] = weight, -weight
    return m


def test_a_converged_solve_is_the_minimiser_a_generic_solver_finds():
    """Eq. 12 on 6×5 pixels against a bounded least-squares solve of its dual.

    Per channel, ``min_z ‖W M z‖₁ + c ‖z − ρ‖²`` (``c = value_scale · γ_a``) has the dual
    ``min_{|u| <= 1} ‖(W M)ᵀ u − 2cρ‖²`` with ``z* = ρ − (W M)ᵀ u* / 2c``: scipy's BVLS solves it
    exactly, and the duality gap certifies it.
    """
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(0)
    labels = np.zeros((6, 5), int)
    labels[:, 3:], labels[4:, :3] = 1, 2
    colours = np.array([[0.60, 0.40, 0.30], [0.25, 0.45, 0.70], [0.55, 0.55, 0.50]])
    rho = colours[labels] + 0.02 * rng.standard_normal((6, 5, 3))
    gpca = np.array([[0.0, 0.1], [0.3, -0.1], [0.05, 0.12]])[labels]
    gpca = gpca + 0.01 * rng.standard_normal((6, 5, 2))
    p = ReflectanceParameters(window=5)  # the paper's gammas and t; a 5×5 window
    m, c = _dense_eq12(rho, gpca, labels, p), p.value_scale * p.gamma_a
    flat_rho = rho.reshape(-1, 3)

    def energy(z):
        return float(np.abs(m @ z).sum() + c * ((z - flat_rho) ** 2).sum())

    ref, dual = np.empty_like(flat_rho), 0.0
    for ch in range(3):
        u = lsq_linear(m.T, 2 * c * flat_rho[:, ch], bounds=(-1, 1), method="bvls", tol=1e-15).x
        g = m.T @ u
        ref[:, ch] = flat_rho[:, ch] - g / (2 * c)
        dual += float(g @ flat_rho[:, ch] - g @ g / (4 * c))
    assert energy(ref) - dual <= 1e-10 * energy(ref)  # certified minimum
    assert np.abs(ref - flat_rho).max() > 0.02  # the priors move z: a real test of them

    to_torch = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].contiguous()  # noqa: E731
    problem = ReflectanceProblem(
        to_torch(rho), to_torch(rho), gpca=to_torch(gpca), segments=torch.from_numpy(labels)[None]
    )
    # Split-Bregman to convergence: tight tolerances, a penalty suited to this problem's scale
    # (the minimiser does not depend on it)
    tight = p.replace(
        theta=320.0, bregman_iter=200, bregman_cg_iter=10, bregman_tol=1e-14, bregman_cg_tol=1e-13
    )
    r = solve_reflectance(problem, tight)
    z = r.reflectance[0].permute(1, 2, 0).reshape(-1, 3).numpy()
    # measured: objective 2e-8 above the minimum, minimiser within 2e-6
    assert energy(ref) <= energy(z) <= energy(ref) * (1 + 1e-6)
    np.testing.assert_allclose(z, ref, atol=2e-5, rtol=0)
    # the stage's own objective is Eq. 12 as written here
    assert float(r.solver.objective[-1, 0]) == pytest.approx(energy(z), rel=1e-9)
