"""torchiid.edit.merging: the merged components of the two stages."""

import torch

from torchiid.edit import Merge, gaussian, merge


def test_merge_of_exact_decomposition_is_identity(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    m = merge(i, r, s, s, r)
    torch.testing.assert_close(m.c, torch.ones_like(m.c), atol=1e-9, rtol=0)
    torch.testing.assert_close(m.shading, s.expand(-1, 3, -1, -1), atol=1e-9, rtol=0)
    torch.testing.assert_close(m.reflectance, r, atol=1e-9, rtol=0)
    torch.testing.assert_close(m.sparse, i)


def test_merge_residue_is_gray_shading_disagreement(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = gaussian(s, 3.0)
    m = merge(i, r, s, sigma, i / sigma, blur=1.0)
    # both stages reconstruct I: C1 = S/σ, C2 = σ/S, gray and >= 1 after averaging
    torch.testing.assert_close(m.c1, (s / sigma).expand(-1, 3, -1, -1))
    torch.testing.assert_close(m.c2, (sigma / s).expand(-1, 3, -1, -1))
    assert float((m.c[:, 0] - m.c[:, 2]).abs().max()) < 1e-9
    assert float(m.c.min()) >= 1 - 1e-9
    # the merged shading lies between the two stages' shadings, and moves off S where they differ
    lo, hi = torch.minimum(s, sigma), torch.maximum(s, sigma)
    merged = m.shading[:, :1]
    assert bool((merged >= lo - 1e-9).all() and (merged <= hi + 1e-9).all())
    differ = (s - sigma).abs() > 0.01
    assert int(differ.sum()) > 50
    assert float((merged - s)[differ].abs().min()) > 0


def test_unfiltered_merge_follows_the_documented_formula(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = 0.8 * s + 0.2 * s.mean()
    m = merge(i, r, s, sigma, i / sigma, blur=0.0)
    c = (s / sigma + sigma / s) / 2
    torch.testing.assert_close(m.shading, ((s / c + sigma * c) / 2).expand(-1, 3, -1, -1))


def test_a_zero_denominator_gives_a_residue_of_one(scene):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = s.clone()
    sigma[..., :8, :] = 0  # outside a Stage 1 mask
    m = merge(i, r, s, sigma, r)
    assert torch.equal(m.c1[..., :8, :], torch.ones_like(m.c1[..., :8, :]))
    assert bool(torch.isfinite(m.shading).all() and torch.isfinite(m.reflectance).all())


def test_module_twin_matches_the_function(scene, one_thread):
    i, r, s = scene.image, scene.reflectance, scene.shading
    sigma = gaussian(s, 2.0)
    got = Merge(blur=1.5)(i, r, s, sigma, r)
    want = merge(i, r, s, sigma, r, blur=1.5)
    assert torch.equal(got.shading, want.shading) and torch.equal(got.c, want.c)
