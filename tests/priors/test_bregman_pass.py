"""The compiled Bregman update agrees with the torch path of ``StencilL1Term``."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.priors import bregman_pass, kernel_runtime, kernels
from torchiid.priors.reflectance_terms import StencilL1Term
from torchiid.priors.stencil import Stencil, half_offsets

pytestmark = [
    pytest.mark.skipif(kernels._numba() is None, reason="needs numba"),
    pytest.mark.usefixtures("kernel_variant"),
]


@pytest.mark.parametrize("history", [0, 1, 2])
def test_replayed_bregman_update_matches_the_stored_state_update(history, monkeypatch, torch_ops):
    """The kernel's right-hand side equals the torch path's update from the stored state
    after the same earlier updates: batch of 2, 11-row-deep pairs, blocks of 8 rows (block
    boundaries inside an image and across the two images, halos of 5 rows)."""
    monkeypatch.setattr(bregman_pass, "REPLAY_BLOCK_ROWS", 8)
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
    fast = bregman_pass.bregman_replay(zs[:-1], zs[-1], w, st.offsets, 0.05)
    torch.testing.assert_close(fast, rhs, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("fixed", [False, True], ids=["float32", "int16"])
def test_stored_state_bregman_updates_match_the_torch_path(fixed, monkeypatch, torch_ops):
    """The compiled update of a stored state (fresh, read and written, read only on the
    final step, warm from a given state, and a replayed state materialised) gives the torch
    path's state, bitwise, and its right-hand side; in float32 and in 16-bit fixed point,
    warm-started from a state written at another threshold."""
    monkeypatch.setattr(bregman_pass, "REPLAY_BLOCK_ROWS", 8)
    g = torch.Generator().manual_seed(11)
    st = Stencil.square(27, 21, 11)
    w = torch.rand(2, st.num_offsets, 27, 21, generator=g) * st.valid
    zs = [torch.rand(2, 3, 27, 21, generator=g) * 0.3 for _ in range(4)]
    valid = st.valid.view(1, 1, st.num_offsets, 27, 21).expand(2, 3, -1, -1, -1)
    shape = (2, 3, st.num_offsets, 27, 21)
    step0 = bregman_pass.fixed_point_scales(0.024)[0]  # the warm state's threshold: not 0.02

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
        step, inv = bregman_pass.fixed_point_scales(0.02)
        assert term.state_step == step
        assert torch.equal(fast[valid], (exact * inv).round().to(torch.int16)[valid])


def test_fixed_point_scales_refuse_thresholds_out_of_range():
    for lam in (0.0, -1.0, 1e-36, float("nan"), float("inf")):
        assert not bregman_pass.fixed_point_fits(lam)
        with pytest.raises(ParameterError, match="cannot be kept in a 16-bit state"):
            bregman_pass.fixed_point_scales(lam)
    assert bregman_pass.fixed_point_fits(1e-30) and bregman_pass.fixed_point_fits(1e30)


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
    step0 = bregman_pass.fixed_point_scales(lam0)[0]
    q0 = torch.randint(-32767, 32768, (1, 3, st.num_offsets, 19, 23), generator=g)
    q0 = q0.to(torch.int16)
    step, inv = bregman_pass.fixed_point_scales(lam)
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
    monkeypatch.setattr(bregman_pass, "REPLAY_BLOCK_ROWS", 4)
    runs = []
    before = torch.get_num_threads()
    try:
        for threads, work in ((1, float("inf")), (2, 0), (3, 0)):
            monkeypatch.setattr(kernel_runtime, "PARALLEL_WORK", work)
            torch.set_num_threads(threads)
            runs.append(bregman_pass.bregman_replay([z0], z1, w, st.offsets, 0.05))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(runs[0], runs[1]) and torch.equal(runs[0], runs[2])


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
