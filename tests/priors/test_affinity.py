import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.affinity import (
    COLOUR_WEIGHTS,
    lab_features,
    merged_stencil_affinity,
    pair_affinity,
    stencil_affinity,
)
from torchiid.priors.stencil import Stencil

D = torch.float64


def _dense_affinity(f, t):
    b, d, h, w = f.shape
    x = f.reshape(b, d, -1)
    d2 = (x.unsqueeze(3) - x.unsqueeze(2)).square().sum(dim=1)
    return torch.exp(-d2 / (2 * t * t))  # (B, N, N)


def test_lab_features_gray_and_scale():
    y = torch.tensor([0.05, 0.2, 0.5, 1.0], dtype=D)
    x = y.view(1, 1, 1, 4).expand(1, 3, 1, 4).clone()
    f = lab_features(x, luminance_weight=0.1)
    lstar = 116 * y ** (1 / 3) - 16  # CIE L* of a linear luminance > 0.008856
    torch.testing.assert_close(f[0, 0, 0], 0.1 * lstar / 100, atol=1e-3, rtol=0)
    assert f[0, 1:].abs().max() < 1e-3  # gray has no chroma
    # reflectance has an arbitrary scale: features ignore it once the white level exceeds 1
    g = torch.Generator().manual_seed(0)
    r = 0.5 + 0.5 * torch.rand(1, 3, 8, 8, generator=g, dtype=D)
    torch.testing.assert_close(lab_features(2 * r), lab_features(5 * r))


def test_stencil_affinity_matches_dense_and_is_symmetric():
    g = torch.Generator().manual_seed(1)
    f = torch.rand(2, 3, 6, 7, generator=g, dtype=D) * 0.1
    st = Stencil.square(6, 7, 5)
    v = stencil_affinity(f, st, 0.05)
    assert v.shape == (2, st.num_offsets, 6, 7)
    assert v.min() >= 0 and v.max() <= 1
    k, i, j = st.pair_index()
    dense = _dense_affinity(f, 0.05)
    ys, xs = i // 7, i % 7
    torch.testing.assert_close(v[:, k, ys, xs], dense[:, i, j])
    # symmetric dense matrix built from the half-stencil weights
    m = torch.zeros(2, 42, 42, dtype=D)
    m[:, i, j] = v[:, k, ys, xs]
    m[:, j, i] = v[:, k, ys, xs]
    assert torch.equal(m, m.transpose(1, 2))
    assert bool((v * ~st.valid).eq(0).all())


def test_stencil_affinity_mask_zeroes_pairs_touching_outside():
    f = torch.rand(1, 3, 6, 6, dtype=D)
    mask = torch.ones(1, 1, 6, 6, dtype=torch.bool)
    mask[0, 0, 2, 3] = False
    st = Stencil.square(6, 6, 3)
    v = stencil_affinity(f, st, 0.5, mask)
    k, i, j = st.pair_index()
    vv = v[0, k, i // 6, i % 6]
    touches = (i == 15) | (j == 15)
    assert bool(vv[touches].eq(0).all()) and bool(vv[~touches].gt(0).all())


def test_merged_affinity_equals_weighted_sum_of_both_terms():
    g = torch.Generator().manual_seed(7)
    colour = torch.rand(2, 3, 9, 10, generator=g, dtype=D) * 0.2
    semantic = torch.rand(2, 4, 9, 10, generator=g, dtype=D) * 0.1
    mask = torch.rand(2, 1, 9, 10, generator=g) > 0.2
    st = Stencil.square(9, 10, 5)
    v_l = stencil_affinity(colour, st, 0.05, mask)
    v_m = v_l * stencil_affinity(semantic, st, 0.07, mask)
    ref = (20.0 * v_l + 5.0 * v_m) / 25.0
    e_g = stencil_affinity(semantic, st, 0.07, mask)
    got = merged_stencil_affinity(colour, e_g, st, 0.05, 20.0, 5.0, mask)
    torch.testing.assert_close(got, ref)
    assert (got <= v_l + 1e-12).all() and (got >= v_m - 1e-12).all()
    torch.testing.assert_close(merged_stencil_affinity(colour, e_g, st, 0.05, 1.0, 0.0, mask), v_l)
    with pytest.raises(ParameterError, match="gamma_l"):
        merged_stencil_affinity(colour, e_g, st, 0.05, 0.0, 0.0)
    with pytest.raises(ShapeError, match="semantic_affinity"):
        merged_stencil_affinity(colour, e_g[:, :3], st, 0.05, 1.0, 1.0)


def test_pair_affinity():
    f = torch.rand(1, 2, 3, 3, dtype=D)
    i, j = torch.tensor([[0, 4]]), torch.tensor([[8, 5]])
    v = pair_affinity(f, i, j, 0.3)
    ff = f.reshape(2, -1)
    ref = torch.exp(-(ff[:, [0, 4]] - ff[:, [8, 5]]).square().sum(0) / (2 * 0.09))
    torch.testing.assert_close(v[0], ref)


def test_a_deviation_must_be_positive():
    with pytest.raises(ParameterError, match="t must be > 0"):
        stencil_affinity(torch.rand(1, 3, 4, 4), Stencil.square(4, 4, 3), 0.0)


def test_bi_colour_weights_match_bi_et_al_at_t_005():
    # Bi et al.'s windowvariation.m: exp(-0.5 * ||(10 L/100, 120 a/220, 120 b/220)||^2)
    g = torch.Generator().manual_seed(3)
    base = 0.1 + 0.8 * torch.rand(1, 3, 1, 1, generator=g, dtype=D)
    # a far pair (weight ~0) and a near pair (weight in (0.05, 0.95)): compare the exponents
    x = torch.cat([base, 0.1 + 0.8 * torch.rand(1, 3, 1, 1, generator=g, dtype=D)], dim=3)
    x = torch.cat([x, base * torch.tensor([1.03, 0.97, 1.0], dtype=D).view(1, 3, 1, 1)], dim=3)
    w_l, scale = COLOUR_WEIGHTS["bi"]
    f = lab_features(x, luminance_weight=w_l, lab_scale=scale)
    lab = lab_features(x, luminance_weight=1.0, lab_scale=(1.0, 1.0, 1.0))
    bi = torch.tensor([10 / 100, 120 / 220, 120 / 220], dtype=D).view(1, 3, 1, 1) * lab
    for j in (1, 2):
        ours = (f[..., 0] - f[..., j]).square().sum() / (2 * 0.05**2)
        ref = 0.5 * (bi[..., 0] - bi[..., j]).square().sum()
        torch.testing.assert_close(ours, ref, rtol=1e-12, atol=0)
    near = torch.exp(-ref)
    assert 0.05 < float(near) < 0.95  # the near pair's weight is informative
