import torch

from torchiid.solvers.smoothers import chebyshev, lanczos_lmax


def _retinex_like(h, w, scale, g):
    """A graph Laplacian with near-binary weights (a dense top of the spectrum) + a small
    diagonal."""
    n = h * w
    idx = torch.arange(n).view(h, w)
    a = torch.zeros(n, n, dtype=torch.float64)
    for i, j in ((idx[:, :-1], idx[:, 1:]), (idx[:-1, :], idx[1:, :])):
        i, j = i.reshape(-1), j.reshape(-1)
        near = torch.rand(i.shape, generator=g, dtype=torch.float64) < 0.7
        wt = torch.where(near, scale, 1e-6 * scale)
        a[i, j] -= wt
        a[j, i] -= wt
        a[i, i] += wt
        a[j, j] += wt
    return a + torch.diag(1e-3 * torch.rand(n, generator=g, dtype=torch.float64))


def test_lambda_max_estimate_is_close_below_the_true_one():
    """15 Lanczos steps land within 1% below the dense eigenvalue of ``D⁻¹A``, never above it,
    in float64 and float32, per batch item."""
    g = torch.Generator().manual_seed(1)
    h, w = 24, 32
    n = h * w
    big = torch.stack([_retinex_like(h, w, s, g) for s in (1.0, 3.0)])  # (2, n, n)
    d = big.diagonal(dim1=1, dim2=2)
    s = d.rsqrt()
    true = torch.linalg.eigvalsh(big * s[:, :, None] * s[:, None, :])[:, -1]

    for dtype in (torch.float64, torch.float32):
        m = big.to(dtype)

        def matvec(v, m=m):
            return torch.bmm(m, v.reshape(2, n, 1)).reshape(v.shape)

        est = lanczos_lmax(matvec, (1 / d).to(dtype).view(2, 1, h, w), 15).flatten().double()
        assert torch.all(est >= 0.99 * true), (est, true)
        assert torch.all(est <= true * (1 + 1e-5)), (est, true)


def test_chebyshev_is_a_symmetric_smoother_that_damps_the_upper_spectrum():
    g = torch.Generator().manual_seed(2)
    h, w = 6, 7
    n = h * w
    a = _retinex_like(h, w, 1.0, g) + torch.eye(n, dtype=torch.float64)
    dinv = (1 / a.diagonal()).view(1, 1, h, w)

    def matvec(v):
        return (a @ v.reshape(n)).view(1, 1, h, w)

    lmax = 1.1 * lanczos_lmax(matvec, dinv, 30)
    # the smoother from 0 is a linear operator S b; it is symmetric (S = p(D⁻¹A) D⁻¹)
    cols = [chebyshev(matvec, dinv, (lmax, 30.0), 3, e.view(1, 1, h, w), None).reshape(n)
            for e in torch.eye(n, dtype=torch.float64)]  # fmt: skip
    smoother = torch.stack(cols, dim=1)
    torch.testing.assert_close(smoother, smoother.T)
    # the error propagation I − S A shrinks the modes of the upper spectrum of D⁻¹A
    error = torch.eye(n, dtype=torch.float64) - smoother @ a
    dh = dinv.reshape(n).sqrt()
    ev, vec = torch.linalg.eigh(dh[:, None] * a * dh[None, :])
    top = dh[:, None] * vec[:, ev > float(lmax) / 30]  # D^-1/2-scaled upper eigenvectors
    assert float((error @ top).norm() / top.norm()) < 0.5
    # from a start x, the same step as from 0 on the residual
    x = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    b = torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    step = chebyshev(matvec, dinv, (lmax, 30.0), 3, b - matvec(x), None)
    torch.testing.assert_close(chebyshev(matvec, dinv, (lmax, 30.0), 3, b, x), x + step)
