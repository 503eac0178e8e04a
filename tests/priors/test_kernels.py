"""The compiled stencil kernels agree with the torch ops they replace."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import ImageError, ShapeError
from torchiid.priors import kernels
from torchiid.priors.matting import MattingQuadratic, matting_stencil
from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.reflectance_terms import StencilL1Term
from torchiid.priors.stencil import Stencil, half_offsets

pytestmark = pytest.mark.skipif(kernels._numba() is None, reason="needs numba")


@pytest.fixture(params=["serial", "parallel"], autouse=True)
def kernel_variant(request, monkeypatch):
    """Every test runs on the calling thread alone, and in row bands on 2 threads."""
    if request.param == "parallel":
        monkeypatch.setattr(kernels, "PARALLEL_WORK", 0)
        before = torch.get_num_threads()
        torch.set_num_threads(2)
        yield request.param
        torch.set_num_threads(before)
    else:
        monkeypatch.setattr(kernels, "PARALLEL_WORK", float("inf"))
        yield request.param


@pytest.fixture
def torch_ops(monkeypatch):
    """Run the block with the torch ops (the reference), as ``TORCHIID_KERNELS=torch`` does."""

    def run(fn):
        with monkeypatch.context() as m:
            m.setattr(kernels, "usable", lambda *t, **k: False)
            return fn()

    return run


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stencil_quadratic_product_matches_torch(torch_ops, dtype):
    g = torch.Generator().manual_seed(0)
    st = Stencil(13, 17, half_offsets(5))
    # signed weights, as the matting Laplacian's stencil has
    w = torch.randn(2, st.num_offsets, 13, 17, generator=g, dtype=dtype)
    x = torch.randn(2, 1, 13, 17, generator=g, dtype=dtype)
    q = StencilQuadratic(st, w)
    assert kernels.usable(x, q.weights)
    fast = q.matvec(x)
    ref = torch_ops(lambda: StencilQuadratic(st, w).matvec(x))
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(fast, ref, rtol=tol, atol=tol)
    # and both equal the assembled matrix
    dense = q.to_sparse().to_dense()
    torch.testing.assert_close(
        fast.reshape(2, -1), (dense @ x.reshape(-1)).reshape(2, -1), rtol=tol, atol=10 * tol
    )


def test_l1_normal_product_matches_torch_on_three_channels(torch_ops):
    g = torch.Generator().manual_seed(1)
    st = Stencil.square(20, 23, 11)  # 60 offsets, reaching 5 pixels past every border
    w = torch.rand(1, st.num_offsets, 20, 23, generator=g)
    z = torch.rand(1, 3, 20, 23, generator=g)
    fast = StencilL1Term(st, w).normal_matvec(z)
    ref = torch_ops(lambda: StencilL1Term(st, w).normal_matvec(z))
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    # not a trivial agreement: the product is far from zero and from the diagonal part alone
    term = StencilL1Term(st, w)
    assert fast.abs().max() > 0.5
    assert (fast - term.normal_diagonal() * z).abs().max() > 0.5


def test_matting_stencil_matches_torch_with_mask(torch_ops):
    g = torch.Generator().manual_seed(2)
    base = torch.rand(2, 3, 16, 19, generator=g)
    mask = torch.rand(2, 1, 16, 19, generator=g) > 0.1
    fast = MattingQuadratic(base, mask=mask).as_stencil()
    ref = torch_ops(lambda: MattingQuadratic(base, mask=mask).as_stencil())
    torch.testing.assert_close(fast.weights, ref.weights, rtol=1e-5, atol=1e-5)
    x = torch.randn(2, 1, 16, 19, generator=g)
    torch.testing.assert_close(
        fast.matvec(x), MattingQuadratic(base, mask=mask).matvec(x), rtol=1e-4, atol=1e-4
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matting_stencil_window_kernel_matches_torch(torch_ops, dtype):
    """The fused path (window statistics and weights in numba) against the torch ops'
    ``MattingQuadratic.as_stencil``, with a mask, a flat patch (only ``eps`` keeps its windows
    invertible) and one outlier pixel (a window of condition number ~1e7)."""
    g = torch.Generator().manual_seed(5)
    base = torch.rand(2, 3, 17, 23, generator=g, dtype=torch.float64)
    base[0, :, 2:9, 3:12] = 0.4  # flat
    base[1, :, 10, 7] = 220.0  # outlier among values near 1
    base = base.to(dtype)
    mask = torch.rand(2, 1, 17, 23, generator=g) > 0.1
    for m in (None, mask):
        fast = matting_stencil(base, 1e-5, m)
        ref = torch_ops(lambda m=m: MattingQuadratic(base, mask=m).as_stencil())
        assert fast.weights.dtype == dtype
        tol = 1e-5 if dtype == torch.float32 else 1e-10
        scale = ref.weights.abs().max()
        torch.testing.assert_close(fast.weights / scale, ref.weights / scale, rtol=0, atol=tol)


def test_matting_stencil_rejects_bad_input():
    with pytest.raises(ImageError, match="3x3"):
        matting_stencil(torch.rand(1, 3, 2, 8))
    with pytest.raises(ShapeError, match="mask"):
        matting_stencil(torch.rand(1, 3, 8, 8), mask=torch.ones(1, 1, 8, 9, dtype=torch.bool))


@pytest.mark.skipif(
    kernels._numba() is None or kernels._numba()[0].config.NUMBA_NUM_THREADS < 2,
    reason="needs numba with 2 threads",
)
def test_result_does_not_depend_on_the_thread_count(monkeypatch):
    monkeypatch.setattr(kernels, "PARALLEL_WORK", 0)
    g = torch.Generator().manual_seed(3)
    st = Stencil.square(40, 31, 11)
    w = torch.rand(1, st.num_offsets, 40, 31, generator=g)
    z = torch.rand(1, 3, 40, 31, generator=g)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # the serial kernel
        one = StencilL1Term(st, w).normal_matvec(z)
        torch.set_num_threads(2)  # the parallel one, on numba's pool
        two = StencilL1Term(st, w).normal_matvec(z)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one, two)


def test_autograd_and_other_dtypes_keep_the_torch_ops():
    x = torch.rand(1, 1, 8, 8, requires_grad=True)
    w = torch.rand(1, 4, 8, 8)
    assert not kernels.usable(x, w)
    with torch.no_grad():
        assert kernels.usable(x, w)
    assert not kernels.usable(x.detach().half(), w.half())
    assert not kernels.usable(x.detach(), w.double())
    # the differentiable loss path still gets a gradient
    q = StencilQuadratic(Stencil.square(8, 8, 3), w)
    q.energy(x).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_environment_switch_turns_the_kernels_off(monkeypatch):
    monkeypatch.setenv("TORCHIID_KERNELS", "torch")
    kernels._numba.cache_clear()
    try:
        assert not kernels.usable(torch.rand(1, 1, 4, 4))
    finally:
        monkeypatch.delenv("TORCHIID_KERNELS")
        kernels._numba.cache_clear()
    assert kernels.usable(torch.rand(1, 1, 4, 4))


@pytest.mark.parametrize("square", [False, True])
def test_degree_matches_the_laplacian_diagonal(square):
    g = torch.Generator().manual_seed(4)
    st = Stencil.square(14, 18, 11)
    w = torch.rand(2, st.num_offsets, 14, 18, generator=g) * st.valid
    fast = kernels.stencil_degree(w, st.offsets, square=square)
    ref = st.laplacian_diagonal(w.square() if square else w)
    torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    # border pixels have fewer pairs: the degree is not a constant
    assert fast[:, :, 7, 9].min() > 1.5 * fast[:, :, 0, 0].max()


@pytest.mark.parametrize("with_mask", [False, True])
def test_affinities_match_torch(torch_ops, with_mask):
    from torchiid.priors.reflectance_terms import merged_stencil_affinity, stencil_affinity

    g = torch.Generator().manual_seed(5)
    st = Stencil.square(15, 21, 11)
    colour = torch.rand(2, 3, 15, 21, generator=g) * 0.1
    feats = torch.rand(2, 7, 15, 21, generator=g) * 0.1
    sem = torch.rand(2, st.num_offsets, 15, 21, generator=g)
    mask = (torch.rand(2, 1, 15, 21, generator=g) > 0.2) if with_mask else None
    fast_m = merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, mask)
    ref_m = torch_ops(lambda: merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, mask))
    torch.testing.assert_close(fast_m, ref_m, rtol=1e-5, atol=1e-6)
    fast_s = stencil_affinity(feats, st, 0.05, mask)
    ref_s = torch_ops(lambda: stencil_affinity(feats, st, 0.05, mask))
    torch.testing.assert_close(fast_s, ref_s, rtol=1e-5, atol=1e-6)
    # weights spread over (0, 1], and exactly 0 where a pair leaves the image
    assert float(fast_m[fast_m > 0].min()) < 0.1 and 0.9 < float(fast_m.max()) <= 1.0 + 1e-6
    assert float(fast_s[:, :, :, -1][:, st.offsets.index((0, 1))].abs().max()) == 0.0


def test_a_forked_child_gets_its_own_band_pool(monkeypatch):
    import os

    first = kernels._executor(1)
    assert kernels._executor(1) is first
    pid = os.getpid()
    monkeypatch.setattr(kernels.os, "getpid", lambda: pid + 1)  # as in a fork's child
    second = kernels._executor(1)
    assert second is not first
    assert second.submit(lambda: 7).result() == 7


def test_inputs_the_kernels_do_not_handle_keep_the_torch_results(torch_ops):
    from torchiid.priors.reflectance_terms import merged_stencil_affinity, stencil_affinity

    g = torch.Generator().manual_seed(6)
    # a mask of batch 1 over a batch of 3 is broadcast
    feats = torch.rand(3, 3, 16, 16, generator=g) * 0.1
    mask = torch.rand(1, 1, 16, 16, generator=g) > 0.3
    st = Stencil.square(16, 16, 5)
    fast = stencil_affinity(feats, st, 0.05, mask)
    torch.testing.assert_close(fast, torch_ops(lambda: stencil_affinity(feats, st, 0.05, mask)))
    # offsets pointing up (dy < 0) are left to the torch ops
    up = Stencil(6, 7, [(-1, 0), (-2, 1)])
    assert not kernels.usable(feats, offsets=up.offsets)
    w = torch.rand(1, 2, 6, 7, generator=g)
    x = torch.rand(1, 1, 6, 7, generator=g)
    dense = StencilQuadratic(up, w).to_sparse().to_dense()
    torch.testing.assert_close(StencilQuadratic(up, w).matvec(x).reshape(-1), dense @ x.reshape(-1))
    # weights of batch 1 for unknowns of batch 2 (broadcast by the torch ops)
    st11 = Stencil.square(16, 16, 11)
    w1 = torch.rand(1, st11.num_offsets, 16, 16, generator=g)
    z2 = torch.rand(2, 3, 16, 16, generator=g)
    fast = StencilL1Term(st11, w1).normal_matvec(z2)
    torch.testing.assert_close(fast, torch_ops(lambda: StencilL1Term(st11, w1).normal_matvec(z2)))
    assert torch.isfinite(fast).all()
    # a non-contiguous out receives the result
    colour = torch.rand(1, 3, 16, 16, generator=g) * 0.1
    sem = torch.rand(1, st.num_offsets, 16, 16, generator=g)
    out = torch.empty(1, 16, 16, st.num_offsets).permute(0, 3, 1, 2)
    got = merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, out=out)
    assert got is out
    torch.testing.assert_close(out, merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0))
    with pytest.raises(ShapeError, match=r"out must be a torch.float32 tensor of shape"):
        merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, out=torch.empty(1, 3, 16, 16))


@pytest.mark.parametrize("history", [0, 1, 2])
def test_replayed_bregman_update_matches_the_stored_state_update(history, monkeypatch, torch_ops):
    """The kernel's right-hand side equals the torch path's update from the stored state
    after the same earlier updates: batch of 2, 11-row-deep pairs, blocks of 8 rows (block
    boundaries inside an image and across the two images, halos of 5 rows)."""
    monkeypatch.setattr(kernels, "REPLAY_BLOCK_ROWS", 8)
    g = torch.Generator().manual_seed(history)
    st = Stencil.square(27, 21, 11)
    w = torch.rand(2, st.num_offsets, 27, 21, generator=g) * st.valid
    zs = [torch.rand(2, 3, 27, 21, generator=g) for _ in range(history + 1)]
    term = StencilL1Term(st, w, zero_invalid=False)

    def reference():
        b = None
        for z in zs:
            b, rhs, _ = term.bregman_step(z, b, 0.05, with_l1=False)
        return rhs

    rhs = torch_ops(reference)
    fast = kernels.bregman_replay(zs[:-1], zs[-1], w, st.offsets, 0.05)
    torch.testing.assert_close(fast, rhs, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("fixed", [False, True], ids=["float32", "int16"])
def test_stored_state_bregman_updates_match_the_torch_path(fixed, monkeypatch, torch_ops):
    """The compiled update of a stored state (fresh, read and written, read only on the
    final step, warm from a given state, and a replayed state materialised) gives the torch
    path's state, bitwise, and its right-hand side; in float32 and in 16-bit fixed point,
    warm-started from a state written at another threshold."""
    monkeypatch.setattr(kernels, "REPLAY_BLOCK_ROWS", 8)
    g = torch.Generator().manual_seed(11)
    st = Stencil.square(27, 21, 11)
    w = torch.rand(2, st.num_offsets, 27, 21, generator=g) * st.valid
    zs = [torch.rand(2, 3, 27, 21, generator=g) * 0.3 for _ in range(4)]
    valid = st.valid.view(1, 1, st.num_offsets, 27, 21).expand(2, 3, -1, -1, -1)
    shape = (2, 3, st.num_offsets, 27, 21)
    step0 = kernels.fixed_point_scales(0.024)[0]  # the warm state's threshold: not 0.02

    def run(keep_state, warm_from=None):
        if warm_from is not None:
            state = warm_from.clone()
        else:  # fixed point: the term's storage decides the format
            state = torch.empty(shape, dtype=torch.int16) if fixed else None
        term = StencilL1Term(st, w, zero_invalid=False, keep_state=keep_state, replay=False,
                             state=state, warm=warm_from is not None,
                             state_step=step0 if fixed else None)  # fmt: skip
        b, out = term.initial_state, []
        for n, z in enumerate(zs):
            final = n == len(zs) - 1
            b, rhs, _ = term.bregman_step(z, b, 0.02, with_l1=False, final=final)
            out.append((None if b is None else b.clone(), rhs, term.state_written))
        return out, term.state_step

    for keep in (True, False):
        warm = torch.rand(shape, generator=g) * 0.048 - 0.024
        if fixed:
            warm = (warm / step0).round().to(torch.int16)
        for start in (None, warm):
            fast, fast_step = run(keep, start)
            ref, ref_step = torch_ops(lambda k=keep, s=start: run(k, s))
            assert fast_step == ref_step
            for (bf, rf, wf), (br, rr, wr) in zip(fast, ref, strict=True):
                assert wf == wr
                torch.testing.assert_close(rf, rr, rtol=1e-5, atol=1e-5)
                if br is not None:  # entries of pairs leaving the image are unspecified
                    assert bf.dtype == (torch.int16 if fixed else torch.float32)
                    assert torch.equal(bf[valid], br[valid])
            # the last update of a solve that keeps no state leaves it as it was
            assert fast[-1][2] is keep
    # a replayed state (default solves) materialised by one compiled call equals the torch one
    storage = torch.empty(shape, dtype=torch.int16) if fixed else None
    term = StencilL1Term(st, w, zero_invalid=False, keep_state=False, state=storage)
    b = None
    for z in zs[:2]:
        b, _, _ = term.bregman_step(z, b, 0.02, with_l1=False)
    assert type(b).__name__ == "_Replay"
    fast = term._materialise(b, compiled=True).clone()
    ref = torch_ops(lambda: term._materialise(b, compiled=False))
    assert torch.equal(fast[valid], ref[valid])
    if fixed:  # replayed in float32 and rounded once: the float32 state, rounded
        float_term = StencilL1Term(st, w, zero_invalid=False, keep_state=False)
        exact = float_term._materialise(b, compiled=True)
        step, inv = kernels.fixed_point_scales(0.02)
        assert term.state_step == step
        assert torch.equal(fast[valid], (exact * inv).round().to(torch.int16)[valid])


def test_fixed_point_scales_refuse_thresholds_out_of_range():
    from torchiid.core.exceptions import ParameterError

    for lam in (0.0, -1.0, 1e-36, float("nan"), float("inf")):
        assert not kernels.fixed_point_fits(lam)
        with pytest.raises(ParameterError, match="cannot be kept in a 16-bit state"):
            kernels.fixed_point_scales(lam)
    assert kernels.fixed_point_fits(1e-30) and kernels.fixed_point_fits(1e30)


def test_fixed_point_state_is_the_float_state_rounded_to_its_step(torch_ops, monkeypatch):
    """A 16-bit state is read as ``q · step`` of the threshold that wrote it and written as
    ``rint(b' · 32767 / λ)``: one update from it equals the float32 update from the decoded
    values, with the new state rounded to the new threshold's step (both paths; on CPU the
    compiled kernel takes it, not the torch ops)."""
    g = torch.Generator().manual_seed(4)
    st = Stencil.square(19, 23, 11)
    w = torch.rand(1, st.num_offsets, 19, 23, generator=g) * st.valid
    z = torch.rand(1, 3, 19, 23, generator=g) * 0.5
    valid = st.valid.view(1, 1, st.num_offsets, 19, 23).expand(1, 3, -1, -1, -1)
    lam0, lam = 0.05, 0.04
    step0 = kernels.fixed_point_scales(lam0)[0]
    q0 = torch.randint(-32767, 32768, (1, 3, st.num_offsets, 19, 23), generator=g)
    q0 = q0.to(torch.int16)
    step, inv = kernels.fixed_point_scales(lam)
    assert step == pytest.approx(lam / 32767, rel=1e-6) and inv == pytest.approx(32767 / lam)

    def update(state, state_step):
        term = StencilL1Term(st, w, zero_invalid=False, state=state, warm=True,
                             state_step=state_step, replay=False)  # fmt: skip
        b, rhs, _ = term.bregman_step(z, term.initial_state, lam, with_l1=False)
        return b, rhs, term.state_step

    def compiled(f):
        with monkeypatch.context() as mp:
            mp.setattr(StencilL1Term, "_torch_step", None)  # a call would fail
            return f()

    for run in (compiled, torch_ops):
        exact, rhs_exact, _ = run(lambda: update(q0.float() * step0, None))
        q, rhs, new_step = run(lambda: update(q0.clone(), step0))
        assert new_step == step
        torch.testing.assert_close(rhs, rhs_exact, rtol=0, atol=0)
        assert torch.equal(q[valid], (exact * inv).round().to(torch.int16)[valid])
        assert int(q[valid].abs().max()) == 32767  # |b'| reaches λ: the full range is used
        err = (q[valid].float() * step - exact[valid]).abs().max()
        assert float(err) <= 0.5 * step * (1 + 1e-3)


def test_replayed_bregman_update_does_not_depend_on_the_thread_count(monkeypatch):
    g = torch.Generator().manual_seed(3)
    st = Stencil.square(45, 23, 11)
    w = torch.rand(1, st.num_offsets, 45, 23, generator=g) * st.valid
    z0, z1 = (torch.rand(1, 3, 45, 23, generator=g) for _ in range(2))
    monkeypatch.setattr(kernels, "REPLAY_BLOCK_ROWS", 4)
    runs = []
    before = torch.get_num_threads()
    try:
        for threads, work in ((1, float("inf")), (2, 0), (3, 0)):
            monkeypatch.setattr(kernels, "PARALLEL_WORK", work)
            torch.set_num_threads(threads)
            runs.append(kernels.bregman_replay([z0], z1, w, st.offsets, 0.05))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(runs[0], runs[1]) and torch.equal(runs[0], runs[2])


def test_affinities_below_the_floor_are_exactly_zero_on_both_paths(torch_ops):
    """Weights under e^MIN_EXPONENT are 0 (their squares would be subnormal), the rest exp."""
    from torchiid.priors.reflectance_terms import (
        MIN_EXPONENT,
        merged_stencil_affinity,
        pair_affinity,
        stencil_affinity,
    )

    t = 0.05
    # one feature along x: the pair (x, x + 1) has exponent -(Δf)² / 2t² from -20.25 to -41.25
    expo = -20.25 - 1.5 * torch.arange(15, dtype=torch.float64)
    steps = (-expo * 2 * t * t).sqrt()
    f = torch.cat([torch.zeros(1), steps.cumsum(0)]).view(1, 1, 1, 16).expand(1, 1, 3, 16)
    st = Stencil(3, 16, [(0, 1)])
    want = torch.where(expo >= MIN_EXPONENT, expo.exp(), torch.zeros_like(expo))
    sem = torch.ones(1, 1, 3, 16)
    colour = f.expand(1, 3, 3, 16) / 3**0.5  # same squared distance over 3 channels
    for fast in (True, False):
        run = (lambda fn: fn()) if fast else torch_ops
        got = run(lambda: stencil_affinity(f.contiguous(), st, t))[0, 0, 1, :15]
        merged = run(lambda: merged_stencil_affinity(colour, sem, st, t, 1.0, 1.0))[0, 0, 1, :15]
        for v in (got, merged):
            torch.testing.assert_close(v.double(), want, rtol=2e-4, atol=0)
            assert bool((v[expo < MIN_EXPONENT] == 0).all()) and bool((v[expo > -29] > 0).all())
    i = torch.arange(15).view(1, 15)
    pair = pair_affinity(f.contiguous(), 16 + i, 16 + i + 1, t)[0]
    torch.testing.assert_close(pair.double(), want, rtol=2e-4, atol=0)


@pytest.mark.parametrize("fixed", [False, True], ids=["float32", "int16"])
def test_bregman_update_stats_match_torch_ops_and_the_definitions(torch_ops, fixed):
    """The measured update: the same state and rhs as without, and the right sums."""
    torch.manual_seed(11)
    st = Stencil(23, 19, half_offsets(5))
    w = torch.rand(2, st.num_offsets, 23, 19) * st.valid
    lam = 0.07
    shape = (2, 3, st.num_offsets, 23, 19)
    z0, z1 = torch.rand(2, 3, 23, 19), torch.rand(2, 3, 23, 19)

    def run(stats):
        state = torch.empty(shape, dtype=torch.int16) if fixed else None
        term = StencilL1Term(st, w, zero_invalid=False, state=state)
        b, _, _ = term.bregman_step(z0, None, lam, with_l1=False)
        before = (b.float() * term.state_step) if fixed else b.clone()
        out = term.bregman_step(z1, b, lam, with_l1=False, stats=stats)
        after = (b.float() * term.state_step) if fixed else b.clone()
        return before, after, out

    before, after, (_, rhs, l1, measured) = run(True)
    _, plain_after, (_, plain_rhs, _) = run(False)
    valid = st.valid.expand(2, 3, -1, -1, -1)
    assert torch.equal(after[valid], plain_after[valid]) and torch.equal(rhs, plain_rhs)
    _, ref_after, (_, ref_rhs, _, ref) = torch_ops(lambda: run(True))
    assert torch.equal(after[valid], ref_after[valid]) and torch.allclose(rhs, ref_rhs, atol=1e-6)
    # the definitions, from dense tensors (float64)
    # (entries of pairs leaving the image are never written: uninitialised, maybe NaN)
    start = torch.where(valid, before.double(), 0.0)
    wz = (w.unsqueeze(1) * st.apply(z1)).double() * valid
    u = wz + start
    new = u.clamp(-lam, lam)
    expect = {
        "l1": wz.abs(), "primal": (new - start).square(),
        "apply_sq": wz.square(), "split_sq": (u - new).square(),
    }  # fmt: skip
    for name, dense in expect.items():
        want = dense.flatten(1).sum(1).float()
        assert torch.allclose(getattr(measured, name), want, rtol=1e-4), name
        assert torch.allclose(getattr(ref, name), want, rtol=1e-4), name
    assert torch.allclose(l1, expect["l1"].flatten(1).sum(1).float(), rtol=1e-4)
    adj = st.adjoint(w.unsqueeze(1).double() * new).float()
    assert torch.allclose(measured.adjoint, adj, atol=1e-5)
    assert torch.allclose(ref.adjoint, adj, atol=1e-5)


def test_rescaled_int16_state_keeps_the_dual_variable():
    """A new threshold reads the same ``q`` as the same ``b / λ`` (no pass over the state)."""
    torch.manual_seed(12)
    st = Stencil(15, 17, half_offsets(3))
    w = torch.rand(1, st.num_offsets, 15, 17) * st.valid
    z = torch.rand(1, 3, 15, 17)
    dense = StencilL1Term(st, w, zero_invalid=False)
    storage = torch.empty(1, 3, st.num_offsets, 15, 17, dtype=torch.int16)
    fixed = StencilL1Term(st, w, zero_invalid=False, state=storage)
    bd, _, _ = dense.bregman_step(z, None, 0.05, with_l1=False)
    bq, _, _ = fixed.bregman_step(z, None, 0.05, with_l1=False)
    bd = dense.rescale_state(bd, 0.05, 0.2)
    bq2 = fixed.rescale_state(bq, 0.05, 0.2)
    assert bq2 is bq
    valid = st.valid.expand(1, 3, -1, -1, -1)
    decoded = bq.float() * fixed.state_step
    assert torch.allclose(decoded[valid], bd[valid], atol=0.2 / 32767)
    assert float(bd[valid].abs().max()) > 0.05  # rescaled beyond the old threshold
