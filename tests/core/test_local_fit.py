import pytest
import torch
import torch.nn.functional as F

from torchiid.core.local_fit import _kernels, _sep, local_linear_residual, residual_in


def _reference(x: torch.Tensor, region: torch.Tensor, sigma: float) -> torch.Tensor:
    """The fit by definition: one weighted least-squares plane per pixel, solved directly."""
    k = _kernels(sigma, torch.float64, x.device)[0]
    r = k.numel() // 2
    g = k[:, None] * k[None, :]
    h, w = x.shape[-2:]
    out = torch.zeros(h, w, dtype=torch.float64)
    m = region[0, 0].double()
    for y in range(h):
        for c in range(w):
            rows, wts, vals = [], [], []
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    yy, xx = y + dy, c + dx
                    if 0 <= yy < h and 0 <= xx < w and m[yy, xx] > 0:
                        rows.append([1.0, dx, dy])
                        wts.append(float(g[dy + r, dx + r]))
                        vals.append(float(x[0, 0, yy, xx]))
            if m[y, c] == 0:
                continue
            a = torch.tensor(rows, dtype=torch.float64)
            wt = torch.tensor(wts, dtype=torch.float64)
            v = torch.tensor(vals, dtype=torch.float64)
            lhs = a.T @ (wt[:, None] * a) + torch.diag(torch.tensor([0.0, 1e-9, 1e-9]))
            coef = torch.linalg.solve(lhs, a.T @ (wt * v))
            out[y, c] = x[0, 0, y, c] - coef[0]
    return out[None, None]


def test_the_fit_is_the_weighted_least_squares_plane_of_each_window():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 1, 12, 14, generator=g, dtype=torch.float64)
    region = torch.rand(1, 1, 12, 14, generator=g) > 0.25
    got = local_linear_residual(x, region, sigma=1.0)
    assert torch.allclose(got, _reference(x, region, 1.0), atol=1e-6)


def test_channels_share_the_fit_and_no_region_is_every_pixel():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 30, 40, generator=g, dtype=torch.float64)
    region = torch.rand(2, 1, 30, 40, generator=g) > 0.3
    together = local_linear_residual(x, region, 2.0)
    apart = torch.cat([local_linear_residual(x[:, i : i + 1], region, 2.0) for i in range(3)], 1)
    assert torch.allclose(together, apart, atol=1e-12)
    everything = torch.ones(2, 1, 30, 40, dtype=torch.bool)
    for sigma in (1.0, 5.0):
        assert torch.allclose(
            local_linear_residual(x, None, sigma), local_linear_residual(x, everything, sigma),
            atol=1e-12,
        )  # fmt: skip
    # float32 window sums: the same residual to float32's precision
    single = local_linear_residual(x, region, 2.0, conv_dtype=torch.float32)
    assert single.dtype == torch.float64
    assert torch.allclose(single, together, atol=1e-5)
    assert torch.equal(residual_in(x, region, 2.0, torch.float32).double(), single)


@pytest.mark.parametrize("sigma", [1.0, 5.0])
def test_the_shifted_sums_are_the_separable_convolution(sigma):
    x = torch.rand(3, 1, 20, 33, dtype=torch.float64)
    k = _kernels(sigma, torch.float64, x.device)
    for ky, kx in ((k[0], k[0]), (k[1], k[2]), (k[2], k[0])):
        ry, rx = ky.numel() // 2, kx.numel() // 2
        ref = F.conv2d(x, ky.view(1, 1, -1, 1), padding=(ry, 0))
        ref = F.conv2d(ref, kx.view(1, 1, 1, -1), padding=(0, rx))
        assert torch.allclose(_sep(x, ky, kx), ref, atol=1e-12)


def test_a_thin_region_and_pixels_outside_give_finite_residuals():
    region = torch.zeros(1, 1, 30, 30, dtype=torch.bool)
    region[..., 10, 5:25] = True  # a one-pixel strip
    region[..., 20, 20] = True  # a lone pixel
    x = torch.rand(1, 2, 30, 30, dtype=torch.float64)
    r = local_linear_residual(x, region, 3.0)
    assert bool(torch.isfinite(r).all())
    assert bool((r[:, :, ~region[0, 0]] == 0).all())
    assert r[..., 20, 20].abs().max().item() < 1e-12  # its own fit


def _solved(x: torch.Tensor, region: torch.Tensor, sigma: float) -> torch.Tensor:
    """The same fit by convolutions and one ``linalg.solve`` per pixel (batches, channels)."""
    k = _kernels(sigma, torch.float64, x.device)
    r = k[0].numel() // 2

    def conv(v, ky, kx):
        v = F.conv2d(v, ky.view(1, 1, -1, 1), padding=(r, 0))
        return F.conv2d(v, kx.view(1, 1, 1, -1), padding=(0, r))

    m = region.double()
    mom = {
        (i, j): conv(m, k[i], k[j])[:, 0]
        for i, j in ((0, 0), (0, 1), (1, 0), (0, 2), (1, 1), (2, 0))
    }
    ridge = 1e-10 * sigma**2 * mom[0, 0].clamp_min(1e-12)
    a = torch.stack(
        [
            torch.stack([mom[0, 0].clamp_min(1e-12), mom[0, 1], mom[1, 0]], -1),
            torch.stack([mom[0, 1], mom[0, 2] + ridge, mom[1, 1]], -1),
            torch.stack([mom[1, 0], mom[1, 1], mom[2, 0] + ridge], -1),
        ],
        -2,
    )
    out = []
    for c in range(x.shape[1]):
        v = x[:, c : c + 1] * m
        rhs = torch.stack([conv(v, k[i], k[j])[:, 0] for i, j in ((0, 0), (0, 1), (1, 0))], -1)
        fit = torch.linalg.solve(a, rhs.unsqueeze(-1))[..., 0, 0]
        out.append(torch.where(region[:, 0], x[:, c] - fit, 0.0))
    return torch.stack(out, 1)


@pytest.mark.parametrize("sigma", [1.0, 3.0, 5.0])
@pytest.mark.parametrize("size", [(2, 3), (17, 23), (40, 31)])
def test_batches_channels_and_tiny_images_match_a_direct_solve(sigma, size):
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2, 3, *size, generator=g, dtype=torch.float64)
    region = torch.rand(2, 1, *size, generator=g) > 0.2
    got = local_linear_residual(x, region, sigma)
    assert torch.allclose(got, _solved(x, region, sigma), atol=1e-9)
    everything = torch.ones(2, 1, *size, dtype=torch.bool)
    assert torch.allclose(
        local_linear_residual(x, None, sigma), _solved(x, everything, sigma), atol=1e-9
    )


@pytest.mark.parametrize("sigma", [1.0, 5.0])
def test_no_region_matches_a_direct_solve_at_sizes_around_its_border_bands(sigma):
    # without a region the weights are solved near the borders and on one whole row and
    # column, and the slopes' sums in bands of r px: sizes at which those bands meet or cross
    r = _kernels(sigma, torch.float64, torch.device("cpu"))[0].numel() // 2
    g = torch.Generator().manual_seed(4)
    for h, w in ((2 * r + 1, 2 * r + 2), (4 * r, 4 * r + 1), (4 * r + 9, 2 * r), (1, 5 * r)):
        x = torch.rand(1, 2, h, w, generator=g, dtype=torch.float64)
        want = _solved(x, torch.ones(1, 1, h, w, dtype=torch.bool), sigma)
        assert torch.allclose(local_linear_residual(x, None, sigma), want, atol=1e-9), (h, w)
        single = residual_in(x.float(), None, sigma, torch.float32)
        assert single.dtype == torch.float32
        assert torch.allclose(single.double(), want, atol=1e-5), (h, w)
