import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torchiid.core.colour import srgb_to_linear
from torchiid.solvers.multigrid import (
    AMGPreconditioner,
    GalerkinMultigrid,
    HSCPreconditioner,
    StencilOperator,
    assemble_csr,
    pcg_callable,
)
from torchiid.stages import ShadingProblem, build_shading_system
from torchiid.stages.shading import anchored_system


@pytest.fixture(scope="module")
def photo_system():
    """The full shading system (the default's five priors, S_s included) of a 96x72 photo."""
    skimage_data = pytest.importorskip("skimage.data")
    from torchiid.features.semantic import semantic_features
    from torchiid.params import Parameters

    rgb = skimage_data.chelsea()
    img = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    img = F.interpolate(srgb_to_linear(img), size=(72, 96), mode="area")
    p = Parameters()
    f = semantic_features(img, p)
    problem = ShadingProblem(img, f.patch_centers, f.patch_features, f.similarity, None, None)
    o = p.shading
    built = build_shading_system(problem, o)
    assert set(built.terms) == {"S_c", "S_p", "S_m", "S_l", "S_s"}
    sys32 = anchored_system(built.total, img, None, o.anchor, o.dark_eps)
    return built.total, sys32


def _float64(system):
    """The same system as a float64 operator (the anchor is below float32 resolution)."""
    op = StencilOperator.from_quadratic(system.total, system.extra, dtype=torch.float64)
    return op, system.rhs.double(), system.x0.double()


def _preconditioners(system, op64):
    pytest.importorskip("pyamg")
    return {
        "torch-mg": GalerkinMultigrid(op64),
        "amg": AMGPreconditioner.from_system(system.total, system.extra),
        "hsc": HSCPreconditioner.from_system(system.total, system.extra),
    }


def test_stencil_operator_and_csr_match_the_system(photo_system):
    total, system = photo_system
    op = StencilOperator.from_quadratic(total, system.extra)
    x = torch.randn(system.rhs.shape, generator=torch.Generator().manual_seed(0))
    ref = system.matvec(x)
    torch.testing.assert_close(op.matvec(x), ref, rtol=1e-4, atol=1e-4 * float(ref.abs().max()))
    torch.testing.assert_close(op.diagonal(), 1 / system.jacobi, rtol=1e-4, atol=1e-6)
    mat = assemble_csr(total, system.extra)
    a = total.to_sparse().coalesce()
    i, j = a.indices().numpy()
    import scipy.sparse as sp

    want = sp.csr_matrix((a.values().double().numpy(), (i, j)), shape=mat.shape)
    want = want + sp.diags(system.extra.double().numpy().ravel())
    assert abs(want - mat).max() <= 1e-5 * abs(want).max()


def test_preconditioners_are_symmetric_positive_definite(photo_system):
    _, system = photo_system
    op64, _, _ = _float64(system)
    g = torch.Generator().manual_seed(1)
    shape = system.rhs.shape
    for name, m in _preconditioners(system, op64).items():
        for _ in range(3):
            x = torch.randn(shape, generator=g, dtype=torch.float64)
            y = torch.randn(shape, generator=g, dtype=torch.float64)
            mx, my = m(x), m(y)
            xmy, ymx = float((x * my).sum()), float((y * mx).sum())
            scale = float(x.norm() * my.norm())
            assert abs(xmy - ymx) <= 1e-9 * scale, name
            assert float((x * mx).sum()) > 0, name
            # smooth vectors too (the near-null space of the Laplacian)
            s = F.avg_pool2d(x, 9, 1, 4, count_include_pad=False)
            assert float((s * m(s)).sum()) > 0, name


def test_pcg_converges_far_faster_than_jacobi_to_the_same_solution(photo_system):
    _, system = photo_system
    op64, b, x0 = _float64(system)
    jac = pcg_callable(op64.matvec, b, x0, 1 / op64.diagonal(), tol=1e-11, max_iter=20000)
    assert jac.converged
    jac_iters = jac.iterations_to(1e-6)
    assert jac_iters > 100
    scale = float(jac.x.abs().max())
    for name, m in _preconditioners(system, op64).items():
        res = pcg_callable(op64.matvec, b, x0, m, tol=1e-11, max_iter=300)
        assert res.converged, name
        assert res.iterations_to(1e-6) <= max(40, jac_iters // 5), (name, jac_iters)
        torch.testing.assert_close(res.x, jac.x, rtol=0, atol=1e-6 * scale)


def test_float32_pcg_with_torch_multigrid(photo_system):
    # the pipeline's dtype: the cycle runs in float32, the coarse solve in float64
    _, system = photo_system
    mg = GalerkinMultigrid.from_system(system.total, system.extra)
    assert mg.levels[0].op.dtype == torch.float32
    res = pcg_callable(system.matvec, system.rhs, system.x0, mg, tol=1e-4, max_iter=100)
    jac = pcg_callable(system.matvec, system.rhs, system.x0, system.jacobi, tol=1e-4, max_iter=5000)
    assert res.converged and jac.converged
    assert res.iterations * 10 < jac.iterations


def test_galerkin_coarse_operator_is_exact():
    # random symmetric 5x5 stencil (signed weights) + a diagonal + two non-local rows
    g = torch.Generator().manual_seed(3)
    h, w = 14, 17
    from torchiid.priors.stencil import half_offsets

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
    op = StencilOperator(offs, a, d, [(m, torch.tensor([0.7, 1.3], dtype=torch.float64))])
    mg = GalerkinMultigrid(op, max_coarse=10)
    assert mg.grid_sizes == [(14, 17), (5, 6)]
    dense = op.to_dense()[0]
    n_c = mg.levels[1].op.numel
    hc, wc = mg.grid_sizes[1]
    p = mg.prolong(0, torch.eye(n_c, dtype=torch.float64).view(n_c, 1, hc, wc).transpose(0, 1))
    p = p.reshape(n_c, h * w).T  # (N, Nc)
    want = p.T @ dense @ p
    got = mg.levels[1].op.to_dense()[0]
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    # restriction is the transpose of prolongation
    r = torch.randn(1, 1, h, w, generator=g, dtype=torch.float64)
    torch.testing.assert_close(mg.restrict(0, r).reshape(-1), p.T @ r.reshape(-1))


def test_batch_equals_items_and_mask(photo_system):
    total, system = photo_system
    op = StencilOperator.from_quadratic(total, system.extra, dtype=torch.float64)
    # a batch of two copies, the second with different weights
    two = StencilOperator(
        op.offsets,
        torch.cat([op.a, 0.5 * op.a]),
        torch.cat([op.d, 0.5 * op.d]),
    )
    one = StencilOperator(op.offsets, 0.5 * op.a, 0.5 * op.d)
    r = torch.randn(2, 1, op.height, op.width, generator=torch.Generator().manual_seed(4))
    r = r.double()
    both = GalerkinMultigrid(two)(r)
    torch.testing.assert_close(both[1:], GalerkinMultigrid(one)(r[1:]), rtol=1e-9, atol=1e-9)
    # masked system: pixels outside are pinned (diag 1), PCG still converges fast
    mask = torch.ones(1, 1, op.height, op.width, dtype=torch.bool)
    mask[..., 10:30, 20:50] = False
    extra = system.extra.double() * mask + (~mask).double()
    mop = StencilOperator.from_quadratic(total, extra, mask=mask, dtype=torch.float64)
    b = system.rhs.double() * mask
    res = pcg_callable(mop.matvec, b, None, GalerkinMultigrid(mop), tol=1e-8, max_iter=200)
    assert res.converged and res.iterations < 60
    assert float(res.x[~mask].abs().max()) < 1e-6


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


def test_lambda_max_estimate_is_close_below_the_true_one():
    """The Chebyshev smoother's ``λ_max(D⁻¹A)``: 15 Lanczos steps on a Retinex-like graph
    Laplacian (near-binary weights, whose top of the spectrum is dense) land within 1% below
    the dense eigenvalue (the power iteration it replaced was 2.8% low: enough for the
    smoother, tuned to 1.1× the estimate, to amplify the modes above it), never above it, in
    float64 and float32, per batch item."""
    from torchiid.solvers.multigrid import _lanczos_lmax

    g = torch.Generator().manual_seed(1)
    h, w = 24, 32
    n = h * w
    idx = torch.arange(n).view(h, w)
    mats = []
    for scale in (1.0, 3.0):
        a = torch.zeros(n, n, dtype=torch.float64)
        for i, j in ((idx[:, :-1], idx[:, 1:]), (idx[:-1, :], idx[1:, :])):
            i, j = i.reshape(-1), j.reshape(-1)
            near = torch.rand(i.shape, generator=g, dtype=torch.float64) < 0.7
            wt = torch.where(near, scale, 1e-6 * scale)
            a[i, j] -= wt
            a[j, i] -= wt
            a[i, i] += wt
            a[j, j] += wt
        a += torch.diag(1e-3 * torch.rand(n, generator=g, dtype=torch.float64))
        mats.append(a)
    big = torch.stack(mats)  # (2, n, n)
    d = big.diagonal(dim1=1, dim2=2)
    s = d.rsqrt()
    true = torch.linalg.eigvalsh(big * s[:, :, None] * s[:, None, :])[:, -1]

    for dtype in (torch.float64, torch.float32):
        m = big.to(dtype)

        def matvec(v, m=m):
            return torch.bmm(m, v.reshape(2, n, 1)).reshape(v.shape)

        est = _lanczos_lmax(matvec, (1 / d).to(dtype).view(2, 1, h, w), 15).flatten().double()
        assert torch.all(est >= 0.99 * true), (est, true)
        assert torch.all(est <= true * (1 + 1e-5)), (est, true)
