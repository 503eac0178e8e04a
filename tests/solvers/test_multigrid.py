import pytest
import torch
import torch.nn.functional as F

from torchiid.core.colour import srgb_to_linear
from torchiid.core.exceptions import ShapeError
from torchiid.priors.stencil import Stencil, half_offsets
from torchiid.solvers.amg import AMGPreconditioner
from torchiid.solvers.hsc import HSCPreconditioner
from torchiid.solvers.multigrid import GalerkinMultigrid
from torchiid.solvers.pcg import pcg_callable
from torchiid.solvers.stencil_operator import StencilOperator
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
    p = Parameters().replace(lambda_s=0.01)  # S_s on: every shading term in the system
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


def test_stencil_operator_is_the_shading_system(photo_system):
    total, system = photo_system
    op = StencilOperator.from_quadratic(total, system.extra)
    x = torch.randn(system.rhs.shape, generator=torch.Generator().manual_seed(0))
    ref = system.matvec(x)
    torch.testing.assert_close(op.matvec(x), ref, rtol=1e-4, atol=1e-4 * float(ref.abs().max()))
    torch.testing.assert_close(op.diagonal(), 1 / system.jacobi, rtol=1e-4, atol=1e-6)


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
    import scipy.sparse.linalg as spla

    _, system = photo_system
    op64, b, x0 = _float64(system)
    exact = torch.from_numpy(spla.spsolve(op64.to_scipy().tocsc(), b.reshape(-1).numpy()))
    exact = exact.view_as(b)
    jac = pcg_callable(op64.matvec, b, x0, 1 / op64.diagonal(), tol=1e-6, max_iter=20000)
    jac_iters = jac.iterations_to(1e-6)
    assert jac.converged and jac_iters > 100
    scale = float(exact.abs().max())
    for name, m in _preconditioners(system, op64).items():
        res = pcg_callable(op64.matvec, b, x0, m, tol=1e-11, max_iter=300)
        assert res.converged, name
        assert res.iterations_to(1e-6) <= max(40, jac_iters // 5), (name, jac_iters)
        torch.testing.assert_close(res.x, exact, rtol=0, atol=1e-6 * scale)


def test_float32_pcg_with_torch_multigrid(photo_system):
    # the pipeline's dtype: the cycle runs in float32, the coarse solve in float64
    _, system = photo_system
    mg = GalerkinMultigrid.from_system(system.total, system.extra)
    assert mg.levels[0].op.dtype == torch.float32
    res = pcg_callable(system.matvec, system.rhs, system.x0, mg, tol=1e-4, max_iter=100)
    jac = pcg_callable(system.matvec, system.rhs, system.x0, system.jacobi, tol=1e-4, max_iter=5000)
    assert res.converged and jac.converged
    assert res.iterations * 10 < jac.iterations


def test_levels_and_their_transfers():
    g = torch.Generator().manual_seed(3)
    h, w = 14, 17
    a = -torch.rand(1, 4, h, w, generator=g, dtype=torch.float64)
    op = StencilOperator(half_offsets(3), a * Stencil.square(h, w, 3).valid, 10 + a[:, :1] ** 2)
    mg = GalerkinMultigrid(op, max_coarse=10)
    assert mg.grid_sizes == [(14, 17), (5, 6)] and mg.operator_complexity() > 1
    xc = torch.randn(1, 1, 5, 6, generator=g, dtype=torch.float64)
    r = torch.randn(1, 1, h, w, generator=g, dtype=torch.float64)
    # restriction is the transpose of prolongation
    torch.testing.assert_close((mg.prolong(0, xc) * r).sum(), (xc * mg.restrict(0, r)).sum())
    with pytest.raises(ShapeError, match="level 1 is the coarsest"):
        mg.prolong(1, xc)
    with pytest.raises(ShapeError, match=r"expected \(B=1, C, 14, 17\)"):
        mg(r[..., :-1])
    with pytest.raises(ValueError, match="block must be >= 2"):
        GalerkinMultigrid(op, block=1)


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
