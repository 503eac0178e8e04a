import pytest
import torch

from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.stencil import Stencil, half_offsets, shift_slices


def _dense_difference(h, w, offsets):
    rows = []
    for dy, dx in offsets:
        for y in range(h):
            for x in range(w):
                yy, xx = y + dy, x + dx
                r = torch.zeros(h * w, dtype=torch.float64)
                if 0 <= yy < h and 0 <= xx < w:
                    r[y * w + x] = 1
                    r[yy * w + xx] = -1
                rows.append(r)
    return torch.stack(rows)  # (K*H*W, H*W), zero rows for invalid pairs


def test_half_offsets_counts_each_pair_once():
    assert len(half_offsets(3)) == 4
    assert len(half_offsets(11)) == 60
    offs = set(half_offsets(5))
    assert not any((-dy, -dx) in offs for dy, dx in offs)
    with pytest.raises(ValueError):
        half_offsets(4)


@pytest.mark.parametrize("size", [3, 5])
def test_apply_adjoint_match_dense(size):
    torch.manual_seed(0)
    h, w = 6, 7
    st = Stencil.square(h, w, size)
    m = _dense_difference(h, w, st.offsets)
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    got = st.apply(x)  # (B, 1, K, H, W)
    ref = (m @ x.reshape(2, -1).T).T.reshape(2, 1, st.num_offsets, h, w)
    torch.testing.assert_close(got, ref)
    d = torch.randn(2, 1, st.num_offsets, h, w, dtype=torch.float64) * st.valid
    ref_adj = (m.T @ d.reshape(2, -1).T).T.reshape(2, 1, h, w)
    torch.testing.assert_close(st.adjoint(d), ref_adj)


def test_laplacian_matvec_diagonal_and_sparse_agree():
    torch.manual_seed(1)
    h, w = 5, 6
    st = Stencil.square(h, w, 3)
    wts = torch.rand(2, st.num_offsets, h, w, dtype=torch.float64)
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    m = _dense_difference(h, w, st.offsets)
    dense = []
    for b in range(2):
        wv = (wts[b] * st.valid).reshape(-1)
        dense.append(m.T @ torch.diag(wv) @ m)
    a = torch.block_diag(*dense)
    torch.testing.assert_close(st.laplacian_matvec(wts, x).reshape(-1), a @ x.reshape(-1))
    torch.testing.assert_close(st.laplacian_diagonal(wts).reshape(-1), a.diagonal())
    d = st.difference_matrix(wts).to_dense()
    torch.testing.assert_close(d.T @ d, a)
    q = StencilQuadratic(st, wts)
    torch.testing.assert_close(q.matvec(x).reshape(-1), a @ x.reshape(-1))
    torch.testing.assert_close(q.to_sparse().to_dense(), a)


def test_stencil_quadratic_target_rhs():
    torch.manual_seed(2)
    h, w = 4, 5
    st = Stencil.square(h, w, 3)
    wts = torch.rand(1, 4, h, w, dtype=torch.float64)
    c = torch.randn(1, 4, h, w, dtype=torch.float64)
    q = StencilQuadratic(st, wts, c)
    x = torch.randn(1, 1, h, w, dtype=torch.float64)
    direct = (wts * st.valid * (st.apply(x)[:, 0] - c) ** 2).sum()
    const = (wts * st.valid * c**2).sum()
    torch.testing.assert_close(q.energy(x)[0] + const, direct)


@pytest.mark.parametrize(("dy", "dx"), [(0, 1), (1, -1), (2, 3), (-1, 0), (0, 0)])
def test_shift_slices_pair_every_inside_pixel_with_its_partner(dy, dx):
    h, w = 5, 7
    idx = torch.arange(h * w).view(h, w)
    yi, xi, yj, xj = shift_slices(dy, dx, h, w)
    i, j = idx[yi, xi].reshape(-1), idx[yj, xj].reshape(-1)
    expect = [
        (y * w + x, (y + dy) * w + x + dx)
        for y in range(h)
        for x in range(w)
        if 0 <= y + dy < h and 0 <= x + dx < w
    ]
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == expect
