import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.reflectance_terms import (
    PairL1Term,
    StencilL1Term,
    _L1Term,
    data_term,
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


def _pair_term(b=2, h=4, w=5, p=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    i = torch.randint(0, h * w, (b, p), generator=g)
    j = torch.randint(0, h * w, (b, p), generator=g)
    wt = torch.rand(b, p, generator=g, dtype=D)
    wt[:, -1] = 0  # a padding pair
    return PairL1Term(i, j, wt, h, w)


def _stencil_term(b=2, h=5, w=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    st = Stencil.square(h, w, 5)
    return StencilL1Term(st, torch.rand(b, st.num_offsets, h, w, generator=g, dtype=D))


def _flat_apply(term, z):
    """apply(z) as (B*P, C) rows in the order of term.matrix()."""
    y = term.apply(z)
    if isinstance(term, StencilL1Term):
        k, i, _ = term.stencil.pair_index()
        w = term.stencil.width
        y = y[:, :, k, i // w, i % w]
    return y.permute(0, 2, 1).reshape(-1, z.shape[1])


@pytest.mark.parametrize("make", [_pair_term, _stencil_term])
def test_operator_matches_sparse_matrix(make):
    term = make()
    b = term.weights.shape[0]
    h, w = (
        (term.height, term.width)
        if isinstance(term, PairL1Term)
        else (term.stencil.height, term.stencil.width)
    )
    g = torch.Generator().manual_seed(3)
    z = torch.rand(b, 3, h, w, generator=g, dtype=D)
    m = term.matrix().to_dense()
    zc = z.permute(0, 2, 3, 1).reshape(-1, 3)  # (B*N, C)
    torch.testing.assert_close(_flat_apply(term, z), m @ zc)
    torch.testing.assert_close(term.l1(z), (m @ zc).abs().reshape(b, -1).sum(1))
    # adjoint: <W M z, y> == <z, (W M)^T y> and equals M^T y of the dense matrix
    y = torch.randn(term.init_state(z).shape, generator=g, dtype=D)
    if isinstance(term, StencilL1Term):
        y = y * term.stencil.valid
    lhs = (term.apply(z) * y).sum()
    rhs = (z * term.adjoint(y)).sum()
    torch.testing.assert_close(lhs, rhs)
    yc = _flat_apply_like(term, y)
    adj = (m.T @ yc).reshape(b, h, w, 3).permute(0, 3, 1, 2)
    torch.testing.assert_close(term.adjoint(y), adj)
    normal = (m.T @ (m @ zc)).reshape(b, h, w, 3).permute(0, 3, 1, 2)
    torch.testing.assert_close(term.normal_matvec(z), normal)
    diag = torch.diagonal(m.T @ m).reshape(b, 1, h, w)
    torch.testing.assert_close(term.normal_diagonal(), diag)


def _flat_apply_like(term, y):
    if isinstance(term, StencilL1Term):
        k, i, _ = term.stencil.pair_index()
        w = term.stencil.width
        y = y[:, :, k, i // w, i % w]
    return y.permute(0, 2, 1).reshape(-1, y.shape[1])


def test_fused_bregman_step_matches_generic():
    term = _stencil_term()
    g = torch.Generator().manual_seed(5)
    z = torch.rand(2, 3, 5, 6, generator=g, dtype=D)
    b0 = torch.randn(term.init_state(z).shape, generator=g, dtype=D) * 0.1 * term.stencil.valid
    b1, r1, l1 = term.bregman_step(z, b0.clone(), 0.05)
    b2, r2, l2 = _L1Term.bregman_step(term, z, b0.clone(), 0.05)
    torch.testing.assert_close(b1, b2)
    torch.testing.assert_close(r1, r2)
    torch.testing.assert_close(l1, l2)
    assert b1.abs().max() <= 0.05 + 1e-12


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


def test_bregman_step_without_l1_gives_the_same_update():
    term = _stencil_term()
    g = torch.Generator().manual_seed(6)
    z = torch.rand(2, 3, 5, 6, generator=g, dtype=D)
    b0 = torch.randn(term.init_state(z).shape, generator=g, dtype=D) * 0.1 * term.stencil.valid
    b1, r1, l1 = term.bregman_step(z, b0.clone(), 0.05, with_l1=False)
    b2, r2, _ = term.bregman_step(z, b0.clone(), 0.05)
    assert l1 is None
    torch.testing.assert_close(b1, b2)
    torch.testing.assert_close(r1, r2)


def test_pair_affinity_and_data_term():
    f = torch.rand(1, 2, 3, 3, dtype=D)
    i, j = torch.tensor([[0, 4]]), torch.tensor([[8, 5]])
    v = pair_affinity(f, i, j, 0.3)
    ff = f.reshape(2, -1)
    ref = torch.exp(-(ff[:, [0, 4]] - ff[:, [8, 5]]).square().sum(0) / (2 * 0.09))
    torch.testing.assert_close(v[0], ref)
    z, r = torch.rand(2, 3, 2, 2, dtype=D), torch.rand(2, 3, 2, 2, dtype=D)
    torch.testing.assert_close(data_term(z, r, 2.0), 2 * ((z - r) ** 2).sum((1, 2, 3)))


def test_errors():
    with pytest.raises(ParameterError, match="t must be > 0"):
        stencil_affinity(torch.rand(1, 3, 4, 4), Stencil.square(4, 4, 3), 0.0)
    with pytest.raises(ParameterError, match=r"expected i, j, weights of one shape \(B, P\)"):
        PairL1Term(
            torch.zeros(1, 3, dtype=torch.long),
            torch.zeros(1, 2, dtype=torch.long),
            torch.zeros(1, 3),
            2,
            2,
        )


def test_bi_colour_weights_match_bi_et_al_at_t_005():
    # Bi et al.'s windowvariation.m: exp(-0.5 * ||(10 L/100, 120 a/220, 120 b/220)||^2)
    from torchiid.priors.reflectance_terms import COLOUR_WEIGHTS

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
