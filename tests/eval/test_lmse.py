import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.eval import local_mse, mit_lmse


def _reference(gt, est, mask, window=20, shift=10):
    """Obviously-correct loop over windows (Grosse's local_error with the energy fix)."""
    rows, cols = gt.shape
    ssq = total = 0.0
    for i in range(0, rows - window + 1, shift):
        for j in range(0, cols - window + 1, shift):
            g = gt[i : i + window, j : j + window]
            e = est[i : i + window, j : j + window]
            m = mask[i : i + window, j : j + window]
            den = np.sum(e**2 * m)
            alpha = np.sum(g * e * m) / den if den > 0 else 0.0
            ssq += np.sum(m * (g - alpha * e) ** 2)
            total += np.sum(m * g**2)
    return ssq / total


def test_local_mse_matches_loop_reference():
    rng = np.random.default_rng(0)
    gt = rng.random((47, 63))
    est = gt * rng.uniform(0.5, 1.5, size=gt.shape) + 0.1 * rng.random(gt.shape)
    mask = rng.random(gt.shape) > 0.3
    mask[:, 40:] = False  # whole windows without mask
    out = local_mse(
        torch.from_numpy(gt)[None, None],
        torch.from_numpy(est)[None, None],
        torch.from_numpy(mask)[None, None],
    )
    assert out.item() == pytest.approx(_reference(gt, est, mask.astype(float)), rel=1e-10)


def test_local_mse_multichannel_is_sum_of_channel_terms():
    g = torch.rand(1, 3, 30, 30, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    e = g + 0.2 * torch.rand(1, 3, 30, 30, dtype=torch.float64)
    num = sum(
        _reference(g[0, c].numpy(), e[0, c].numpy(), np.ones((30, 30)))
        * np.sum(_energy(g[0, c].numpy()))
        for c in range(3)
    )
    den = sum(np.sum(_energy(g[0, c].numpy())) for c in range(3))
    assert local_mse(g, e).item() == pytest.approx(num / den, rel=1e-10)


def _energy(g, window=20, shift=10):
    return [
        np.sum(g[i : i + window, j : j + window] ** 2)
        for i in range(0, g.shape[0] - window + 1, shift)
        for j in range(0, g.shape[1] - window + 1, shift)
    ]


def test_local_mse_zero_for_gt_and_scaled_gt():
    g = torch.rand(2, 1, 40, 50, generator=torch.Generator().manual_seed(2)) + 0.1
    assert torch.allclose(local_mse(g, g), torch.zeros(2), atol=1e-12)
    assert torch.allclose(local_mse(g, 3.7 * g), torch.zeros(2), atol=1e-12)
    assert torch.allclose(local_mse(g, 1e-6 * g), torch.zeros(2), atol=1e-12)
    # a per-window scale change (piecewise scale across windows) is also forgiven
    est = g.clone()
    est[..., :20, :20] *= 5.0
    assert local_mse(g, est).max() > 0  # windows straddling the change see an error


def test_local_mse_constant_estimate_by_hand():
    # one 2x2 window: alpha*c = mean(gt) = 2.5, error 5, energy 30
    gt = torch.tensor([[1.0, 2.0], [3.0, 4.0]])[None, None]
    assert local_mse(gt, torch.full_like(gt, 0.3), window=2).item() == pytest.approx(1 / 6)
    # two overlapping windows (shift 1): errors 10 + 10, energies 46 + 74
    gt = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])[None, None]
    out = local_mse(gt, torch.ones_like(gt), window=2, shift=1)
    assert out.item() == pytest.approx(20 / 120)


def test_local_mse_zero_estimate_gives_one():
    g = torch.rand(1, 1, 20, 20) + 0.1
    assert local_mse(g, torch.zeros_like(g)).item() == pytest.approx(1.0)


def test_mit_lmse_properties():
    gen = torch.Generator().manual_seed(3)
    s = torch.rand(1, 1, 40, 40, generator=gen) + 0.1
    r = torch.rand(1, 3, 40, 40, generator=gen) + 0.1
    mask = torch.rand(1, 1, 40, 40, generator=gen) > 0.2
    assert mit_lmse(r, s, 0.5 * r, 2 * s, mask).item() == pytest.approx(0.0, abs=1e-12)
    # 3-channel shading is reduced to gray; gray reflectance estimate is accepted
    out = mit_lmse(r, s, r.mean(1, keepdim=True), s.expand(1, 3, 40, 40), mask)
    assert out.item() == pytest.approx(0.0, abs=1e-12)
    ones = torch.ones_like(s)
    half = 0.5 * local_mse(s, ones, mask) + 0.5 * local_mse(r.mean(1, keepdim=True), ones, mask)
    assert mit_lmse(r, s, ones, ones, mask).item() == pytest.approx(half.item())
    assert 0 < mit_lmse(r, s, ones, ones, mask).item() < 1


def test_lmse_errors():
    g = torch.rand(1, 1, 30, 30)
    with pytest.raises(ShapeError):
        local_mse(g, torch.rand(1, 1, 30, 31))
    with pytest.raises(ShapeError):
        local_mse(torch.rand(1, 1, 10, 10), torch.rand(1, 1, 10, 10))
    with pytest.raises(ShapeError):
        local_mse(g, g, mask=torch.ones(1, 1, 29, 30))
    with pytest.raises(ShapeError):
        mit_lmse(torch.rand(1, 2, 30, 30), g, g, g)


def test_mit_lmse_and_local_mse_take_one_unbatched_image():
    # a dataset sample's layers are (C, H, W): they score without adding a batch axis
    gen = torch.Generator().manual_seed(4)
    r = torch.rand(3, 40, 44, generator=gen) + 0.1
    s = torch.rand(1, 40, 44, generator=gen) + 0.1
    est_r = r * (torch.rand(3, 40, 44, generator=gen) + 0.5)
    est_s = torch.rand(1, 40, 44, generator=gen) + 0.1
    mask = torch.rand(1, 40, 44, generator=gen) > 0.2
    batched = mit_lmse(r[None], s[None], est_r[None], est_s[None], mask[None])
    for m in (mask, mask[0]):  # (1, H, W) and (H, W) masks
        one = mit_lmse(r, s, est_r, est_s, m)
        assert one.shape == () and one.item() == pytest.approx(batched.item(), rel=1e-12)
    one = local_mse(s, est_s, mask)
    assert one.shape == () and one.item() == pytest.approx(
        local_mse(s[None], est_s[None], mask[None]).item(), rel=1e-12
    )
    assert mit_lmse(r, s, 0.5 * r, 2 * s).item() == pytest.approx(0.0, abs=1e-12)


def test_mit_lmse_refuses_batched_and_unbatched_layers_mixed():
    r, s = torch.rand(3, 30, 30) + 0.1, torch.rand(1, 30, 30) + 0.1
    with pytest.raises(ShapeError, match=r"all batched \(B, C, H, W\) or all one image"):
        mit_lmse(r, s, r[None], s[None])
    with pytest.raises(ShapeError, match=r"est has shape \(1, 1, 30, 30\) but gt"):
        local_mse(s, s[None])
    with pytest.raises(ShapeError, match=r"\(B, C, H, W\) or \(C, H, W\), got \(30, 30\)"):
        mit_lmse(r[0], s[0], r[0], s[0])
