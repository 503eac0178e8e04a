import math

import pytest
import torch

from torchiid.core.exceptions import ImageError
from torchiid.priors.matting import matting_laplacian, smooth_base


def _dense_matting(img, eps, mask=None):
    """Levin et al. Eq. 12, one window at a time (obviously correct, slow)."""
    b, _, h, w = img.shape
    out = torch.zeros(b * h * w, b * h * w, dtype=torch.float64)
    for n in range(b):
        for y in range(1, h - 1):
            for x in range(1, w - 1):
                ids = [(y + dy) * w + (x + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
                if mask is not None and not bool(mask[n, 0].reshape(-1)[ids].all()):
                    continue
                z = img[n].reshape(3, -1)[:, ids].T
                mu = z.mean(0)
                cov = (z - mu).T @ (z - mu) / 9
                inv = torch.linalg.inv(cov + eps / 9 * torch.eye(3, dtype=torch.float64))
                g = torch.eye(9, dtype=torch.float64) - (1 + (z - mu) @ inv @ (z - mu).T) / 9
                gi = [n * h * w + i for i in ids]
                for a in range(9):
                    for c in range(9):
                        out[gi[a], gi[c]] += g[a, c]
    return out


@pytest.fixture
def image():
    torch.manual_seed(0)
    img = torch.rand(2, 3, 8, 8, dtype=torch.float64)
    img[:, :, :4, :4] = 0.4  # a flat region: the nearly singular eps-dominated case
    img[1, :, 4:, :] *= 0.1
    return img


def test_matches_dense_reference(image):
    ref = _dense_matting(image, 1e-5)
    lap = matting_laplacian(image, eps=1e-5)
    torch.testing.assert_close(lap.to_sparse().to_dense(), ref)
    x = torch.randn(2, 1, 8, 8, dtype=torch.float64)
    torch.testing.assert_close(lap.matvec(x).reshape(-1), ref @ x.reshape(-1))
    torch.testing.assert_close(lap.diagonal().reshape(-1), ref.diagonal(), atol=1e-6, rtol=1e-8)


def test_rows_sum_to_zero_and_psd(image):
    a = matting_laplacian(image).to_sparse().to_dense()
    torch.testing.assert_close(
        a.sum(1), torch.zeros(a.shape[0], dtype=torch.float64), atol=1e-8, rtol=0
    )
    torch.testing.assert_close(a, a.T)
    ev = torch.linalg.eigvalsh(a)
    assert float(ev.min()) > -1e-8 * float(ev.max())


def test_window_with_an_outlier_pixel_stays_psd():
    # a later alternation's base is the previous reflectance, where a dark pixel at the mask's
    # edge can reach 220 among values near 2 (MIT's frog1): its windows' covariances have a
    # condition number near 1e8. The adjugate inverse lost 0.75% there and gave the Laplacian
    # (and its stencil form, the solver's) an eigenvalue of -0.18 and negative diagonal entries
    g = torch.Generator().manual_seed(4)
    shade = 1.6 + 0.4 * torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64)
    tint = torch.tensor([1.0, 1.04, 0.82], dtype=torch.float64).view(1, 3, 1, 1)
    img = shade * tint * (1 + 0.02 * torch.rand(1, 3, 8, 8, generator=g, dtype=torch.float64))
    img[0, :, 4, 3] = torch.tensor([220.2, 244.3, 196.8], dtype=torch.float64)
    ref = _dense_matting(img, 1e-5)
    lap = matting_laplacian(img)
    torch.testing.assert_close(lap.to_sparse().to_dense(), ref, atol=1e-6, rtol=1e-6)
    stencil = lap.as_stencil()
    assert float(stencil.diagonal().min()) >= 0
    ev = torch.linalg.eigvalsh(stencil.to_sparse().to_dense())
    assert float(ev.min()) > -1e-6 * float(ev.max())


def test_float32_fast_product_close_to_float64(image):
    ref = _dense_matting(image, 1e-5)
    lap = matting_laplacian(image.float())
    x = torch.randn(2, 1, 8, 8, dtype=torch.float64)
    got = lap.matvec(x.float()).double().reshape(-1)
    want = ref @ x.reshape(-1)
    assert float((got - want).norm() / want.norm()) < 1e-4


def test_mask_drops_windows(image):
    mask = torch.ones(2, 1, 8, 8, dtype=torch.bool)
    mask[0, 0, 2, 5] = False
    mask[1, 0, 6:, :] = False
    lap = matting_laplacian(image, mask=mask)
    ref = _dense_matting(image, 1e-5, mask)
    torch.testing.assert_close(lap.to_sparse().to_dense(), ref)
    x = torch.randn(2, 1, 8, 8, dtype=torch.float64)
    torch.testing.assert_close(lap.matvec(x).reshape(-1), ref @ x.reshape(-1))
    # the pixel outside the mask is decoupled from everything
    assert float(ref[2 * 8 + 5].abs().max()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.6, 1.0, 2.0])
def test_smooth_base_matches_scipy_gaussian_filter(dtype, sigma):
    from scipy.ndimage import gaussian_filter

    x = torch.rand(2, 3, 13, 17, generator=torch.Generator().manual_seed(4), dtype=dtype)
    radius = math.ceil(3 * sigma)
    # torch's "reflect" padding leaves the edge pixel out, scipy's "mirror"
    ref = gaussian_filter(x.double().numpy(), (0, 0, sigma, sigma), mode="mirror", radius=radius)
    out = smooth_base(x, sigma)
    assert out.dtype == dtype and out.shape == x.shape
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out.double(), torch.from_numpy(ref), atol=tol, rtol=0)
    # the taps reach beyond a tiny image: replicate padding, still a normalised average
    tiny = torch.rand(1, 3, 2, 3, dtype=dtype)
    out = smooth_base(tiny, 1.0)
    assert out.shape == tiny.shape and bool((out >= tiny.min()).all() & (out <= tiny.max()).all())


def test_smooth_base_keeps_constants_and_errors():
    flat = torch.full((1, 3, 10, 12), 0.3)
    torch.testing.assert_close(smooth_base(flat, 1.5), flat)
    assert smooth_base(torch.rand(1, 3, 4, 4), 2.0).shape == (1, 3, 4, 4)
    with pytest.raises(ImageError):
        matting_laplacian(torch.rand(1, 3, 2, 8))
    bad = torch.rand(1, 3, 8, 8)
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ImageError, match="NaN"):
        matting_laplacian(bad)


def test_stencil_form_equals_reference(image):
    mask = torch.ones(2, 1, 8, 8, dtype=torch.bool)
    mask[1, 0, 5, 2] = False
    for m in (None, mask):
        lap = matting_laplacian(image, mask=m)
        st = lap.as_stencil(band_rows=3)  # several row bands on an 8-row image
        torch.testing.assert_close(st.weights, lap.as_stencil().weights)
        ref = _dense_matting(image, 1e-5, m)
        torch.testing.assert_close(st.to_sparse().to_dense(), ref)
        x = torch.randn(2, 1, 8, 8, dtype=torch.float64)
        torch.testing.assert_close(st.matvec(x).reshape(-1), ref @ x.reshape(-1))
        torch.testing.assert_close(st.diagonal().reshape(-1), ref.diagonal(), atol=1e-6, rtol=1e-8)


def test_float32_stencil_and_diagonal_close_to_float64(image):
    ref = _dense_matting(image, 1e-5)
    lap = matting_laplacian(image.float())
    st = lap.as_stencil()
    assert st.weights.dtype == torch.float32
    a = st.to_sparse().to_dense().double()
    assert float((a - ref).abs().max() / ref.abs().max()) < 1e-5
    diag = lap.diagonal().double().reshape(-1)
    assert float((diag - ref.diagonal()).abs().max() / ref.diagonal().max()) < 1e-5
