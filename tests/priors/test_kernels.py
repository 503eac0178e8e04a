"""The compiled stencil kernels agree with the torch ops they replace."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import ImageError, ShapeError
from torchiid.priors import kernel_runtime, kernels
from torchiid.priors.matting import MattingQuadratic, matting_stencil
from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.reflectance_terms import StencilL1Term
from torchiid.priors.stencil import Stencil, half_offsets

pytestmark = [
    pytest.mark.skipif(kernels._numba() is None, reason="needs numba"),
    pytest.mark.usefixtures("kernel_variant"),
]


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
    monkeypatch.setattr(kernel_runtime, "PARALLEL_WORK", 0)
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


@pytest.mark.parametrize("with_mask", [False, True])
def test_merged_weights_written_over_their_factor_are_the_same_on_both_paths(torch_ops, with_mask):
    from torchiid.priors.reflectance_terms import merged_stencil_affinity

    g = torch.Generator().manual_seed(9)
    st = Stencil.square(14, 19, 11)  # 60 offsets: groups of 8, the last one short
    colour = torch.rand(2, 3, 14, 19, generator=g) * 0.1
    sem = torch.rand(2, st.num_offsets, 14, 19, generator=g)
    mask = (torch.rand(2, 1, 14, 19, generator=g) > 0.2) if with_mask else None
    want = merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, mask)
    for run in (lambda f: f(), torch_ops):  # the kernels, then the torch ops
        factor = sem.clone()
        got = run(
            lambda f=factor: merged_stencil_affinity(colour, f, st, 0.05, 2.0, 20.0, mask, out=f)
        )
        assert got.data_ptr() == factor.data_ptr()
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    # each path's values are those it writes to a new tensor, bit for bit
    factor = sem.clone()
    assert torch.equal(
        merged_stencil_affinity(colour, factor, st, 0.05, 2.0, 20.0, mask, out=factor), want
    )
    fresh = torch_ops(lambda: merged_stencil_affinity(colour, sem, st, 0.05, 2.0, 20.0, mask))
    factor = sem.clone()
    over = torch_ops(
        lambda: merged_stencil_affinity(colour, factor, st, 0.05, 2.0, 20.0, mask, out=factor)
    )
    assert torch.equal(over, fresh)
    # memory shared in any other way than as the same contiguous tensor is refused
    with pytest.raises(ShapeError, match="is another view of it: pass semantic_affinity itself"):
        view = sem.permute(0, 1, 3, 2).contiguous().permute(0, 1, 3, 2)
        merged_stencil_affinity(colour, view, st, 0.05, 2.0, 20.0, out=view)
    square = Stencil.square(12, 12, 5)
    s12 = torch.rand(1, square.num_offsets, 12, 12, generator=g)
    with pytest.raises(ValueError, match="different views"):
        kernels.stencil_affinity(
            colour[:1, :, :12, :12], square.offsets, -200.0, s12.transpose(-1, -2), 1.0, 1.0,
            out=s12,
        )  # fmt: skip


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
