"""The public priors: operator == exact sparse matrix, symmetry, PSD, batch == one by one."""

from __future__ import annotations

import pytest
import torch

from torchiid.losses import image_priors
from torchiid.params import Parameters
from torchiid.priors import PairL1Term, ReflectancePrior, ShadingPrior, reflectance_priors
from torchiid.synthetic import mondrian

PARAMS = Parameters().replace(patch_size=8, patch_stride=4, lambda_s=0.01)  # S_s on too


@pytest.fixture(scope="module")
def batch():
    img = mondrian(16, 20, batch=2, dtype=torch.float64).image
    return img, image_priors(img, PARAMS)


def test_every_prior_is_built_separately(batch):
    _, pr = batch
    assert set(pr.shading) == {"S_c", "S_p", "S_m", "S_l", "S_s"}
    assert set(pr.reflectance) == {"A", "B", "C"}
    assert all(isinstance(p, ShadingPrior) and p.equation for p in pr.shading.values())
    assert all(isinstance(p, ReflectancePrior) and p.equation for p in pr.reflectance.values())
    merged = image_priors(batch[0], PARAMS, merge=True)
    assert set(merged.reflectance) == {"A+B", "C"}


def test_shading_operator_equals_sparse_symmetric_psd(batch):
    _, pr = batch
    g = torch.Generator().manual_seed(0)
    for name, p in pr.shading.items():
        a = p.to_sparse()
        assert a.layout == torch.sparse_coo and a.shape == (2 * 320, 2 * 320)
        x = torch.randn(p.shape, dtype=torch.float64, generator=g)
        torch.testing.assert_close(a @ x.reshape(-1), p.matvec(x).reshape(-1), msg=name)
        csr = p.to_sparse(torch.sparse_csr)
        torch.testing.assert_close(csr @ x.reshape(-1), p.matvec(x).reshape(-1), msg=name)
        dense = a.to_dense()
        torch.testing.assert_close(dense, dense.T, msg=name)
        assert torch.linalg.eigvalsh(dense).min() > -1e-8 * dense.abs().max(), name
        # block-diagonal: no coupling between the two images
        assert dense[:320, 320:].abs().max() == 0, name
        # the energy is the sum of squared residuals: non-negative
        assert bool((p.energy(x) >= -1e-9).all()), name


def test_reflectance_operator_equals_sparse(batch):
    _, pr = batch
    z = torch.rand(2, 3, 16, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    for name, p in pr.reflectance.items():
        m = p.to_sparse()
        assert m.shape == (2 * p.num_rows, 2 * 320), name
        y = p.apply(z)
        for c in range(3):
            got = (m @ z[:, c].reshape(-1)).view(2, -1)
            torch.testing.assert_close(got, y[:, c].reshape(2, -1), msg=name)
        torch.testing.assert_close(p.l1(z), y.abs().flatten(1).sum(1))
        # W M annihilates constants; its normal matrix is the solver's z-step operator
        assert bool(((m @ torch.ones(2 * 320, dtype=torch.float64)).abs() < 1e-12).all()), name
        mt = p.adjoint(y)
        dense = m.to_dense()
        for c in range(3):
            want = (dense.T @ dense @ z[:, c].reshape(-1)).view(2, 16, 20)
            torch.testing.assert_close(mt[:, c], want, msg=name)
            torch.testing.assert_close(p.term.normal_matvec(z)[:, c], want, msg=name)


def test_batch_equals_one_by_one(batch):
    img, pr = batch
    x = torch.randn(2, 1, 16, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    z = torch.rand(2, 3, 16, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    for b in range(2):
        one = image_priors(img[b : b + 1], PARAMS)
        for name, p in one.shading.items():
            full = pr.shading[name]
            torch.testing.assert_close(p.matvec(x[b : b + 1]), full.matvec(x)[b : b + 1])
            torch.testing.assert_close(p.energy(x[b : b + 1]), full.energy(x)[b : b + 1])
            n = 320
            blk = full.to_sparse().to_dense()[b * n : (b + 1) * n, b * n : (b + 1) * n]
            torch.testing.assert_close(p.to_sparse().to_dense(), blk, msg=name)
        for name, p in one.reflectance.items():
            full = pr.reflectance[name]
            torch.testing.assert_close(p.l1(z[b : b + 1]), full.l1(z)[b : b + 1], msg=name)


def test_masked_priors_ignore_the_outside():
    img = mondrian(16, 16, dtype=torch.float64).image
    mask = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
    mask[..., 2:14, 3:13] = True
    pr = image_priors(img, PARAMS, mask=mask)
    x = torch.randn(1, 1, 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    y = x.clone()
    y[~mask] = 5.0
    for name, p in pr.shading.items():
        torch.testing.assert_close(p.energy(x), p.energy(y), msg=name)


def test_pair_prior_operator_equals_sparse():
    """``C``'s layout on explicit pairs (the tiny images above have one segment each)."""
    g = torch.Generator().manual_seed(5)
    i = torch.randint(0, 48, (2, 7), generator=g)
    j = torch.randint(0, 48, (2, 7), generator=g)
    w = torch.rand(2, 7, dtype=torch.float64, generator=g)
    p = reflectance_priors({"C": (2.0, PairL1Term(i, j, w, 6, 8))})["C"]
    assert p.weight == 2.0 and "Eq. 10" in p.equation
    z = torch.rand(2, 3, 6, 8, dtype=torch.float64, generator=g)
    m = p.to_sparse()
    assert m.shape == (14, 96)
    for c in range(3):
        torch.testing.assert_close((m @ z[:, c].reshape(-1)).view(2, -1), p.apply(z)[:, c])
