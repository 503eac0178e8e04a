import numpy as np
import pytest
import torch
from skimage import data, transform

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.midlevel import (
    MidLevelBatch,
    midlevel_features,
    midlevel_features_batch,
)
from torchiid.features.proposals import Proposals, selective_search
from torchiid.priors.stencil import Stencil, half_offsets

H, W = 40, 56


@pytest.fixture(scope="module")
def props():
    img = transform.resize(data.chelsea(), (H, W), anti_aliasing=True)
    return selective_search(img, scales=(30, 80), max_proposals=150)


@pytest.fixture(scope="module")
def mid(props):
    return midlevel_features(props, dtype=torch.float64)


def _dense_reference(p: Proposals) -> torch.Tensor:
    """(P, H, W) float64 g from dense masks."""
    g = p.masks().double() * p.scores.double().view(-1, 1, 1)
    n = g.norm(dim=0, keepdim=True)
    return torch.where(n > 0, g / n.clamp_min(1e-300), g)


def test_dense_matches_reference_and_unit_norm(props, mid):
    dense = mid.dense()
    assert dense.shape == (1, props.num_proposals, H, W) and dense.dtype == torch.float64
    ref = _dense_reference(props)
    torch.testing.assert_close(dense[0], ref, rtol=0, atol=1e-12)
    norm = dense[0].norm(dim=0)
    torch.testing.assert_close(norm, torch.ones_like(norm), rtol=0, atol=1e-12)


@pytest.mark.parametrize("size", [3, 5])
def test_similarity_matches_dense(mid, size):
    st = Stencil.square(H, W, size)
    sim = mid.similarity(st)
    assert sim.shape == (1, st.num_offsets, H, W) and sim.dtype == torch.float64
    g = mid.dense()[0]
    ref = torch.zeros(st.num_offsets, H, W, dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    for k, (dy, dx) in enumerate(half_offsets(size)):  # dense per-pixel products
        inside = (ys + dy >= 0) & (ys + dy < H) & (xs + dx >= 0) & (xs + dx < W)
        y, x = ys[inside], xs[inside]
        ref[k, y, x] = (g[:, y, x] * g[:, y + dy, x + dx]).sum(0)
    torch.testing.assert_close(sim[0], ref, rtol=0, atol=1e-12)
    same = st.valid & (mid.atom_labels == st.neighbours(mid.atom_labels.view(1, 1, H, W))[0, 0])
    assert bool((sim[0][same] == 1).all())
    assert bool((sim[0][~st.valid] == 0).all())


def _dense_pca(p: Proposals, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    x = _dense_reference(p).flatten(1).T  # (N, P)
    xc = x - x.mean(0)
    evals, evecs = torch.linalg.eigh(xc.T @ xc / x.shape[0])
    v = evecs.flip(1)[:, :dim]
    return (xc @ v).T.reshape(dim, H, W), evals.flip(0)[:dim]


@pytest.mark.parametrize("method", ["exact", "randomized"])
def test_pca_matches_dense_reference(props, mid, method):
    dim = 4
    z = mid.pca(dim, method)
    assert z.shape == (1, dim, H, W) and z.dtype == torch.float64
    ref, ref_var = _dense_pca(props, dim)
    _, var = mid.pca_atoms(dim, method)
    torch.testing.assert_close(var, ref_var, rtol=1e-6, atol=1e-10)
    gaps = (ref_var[:-1] - ref_var[1:]) / ref_var[0]
    assert bool((gaps[:3] > 1e-3).all()), "test needs separated components"
    for c in range(dim - 1):  # components with a spectral gap agree up to sign
        sign = torch.sign((z[0, c] * ref[c]).sum())
        torch.testing.assert_close(z[0, c] * sign, ref[c], rtol=0, atol=1e-5)
    # projections are centred and their variance is the eigenvalue
    torch.testing.assert_close(
        z[0].flatten(1).mean(1), torch.zeros(dim, dtype=torch.float64), rtol=0, atol=1e-10
    )
    torch.testing.assert_close(z[0].flatten(1).var(1, correction=0), var, rtol=1e-6, atol=1e-10)


def test_pca_sign_convention_and_methods_agree(props, mid):
    a = mid.pca(3, "exact")
    b = mid.pca(3, "randomized")
    torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    again = midlevel_features(props, dtype=torch.float64)
    torch.testing.assert_close(again.pca(3), a, rtol=0, atol=0)
    # the pixel-weighted covariance times the components: C V = V diag(var), so the columns
    # of (g - mu)^T diag(w) proj are the component vectors scaled by their (positive) variances
    wn = (mid.atom_sizes / mid.atom_sizes.sum()).to(mid.atom_g.dtype).unsqueeze(1)
    gc = mid.atom_g - (wn * mid.atom_g).sum(0)
    v = gc.T @ (wn * mid.pca_atoms(3, "exact")[0])
    top = v.abs().argmax(0)
    assert bool((v[top, torch.arange(3)] > 0).all())


def test_two_flat_regions_similarity():
    img = np.zeros((20, 30, 3))
    img[:, :12] = (0.8, 0.7, 0.1)
    img[:, 12:] = (0.1, 0.3, 0.8)
    p = selective_search(img, scales=(50,), colour_spaces=("rgb", "lab"))
    g = midlevel_features(p).dense()[0]
    same = float(g[:, 5, 2] @ g[:, 15, 8])
    across = float(g[:, 5, 2] @ g[:, 5, 25])
    assert same == pytest.approx(1.0, abs=1e-6)
    assert across < same - 0.1
    sim = midlevel_features(p).similarity(Stencil.square(20, 30, 3))[0, 0]  # offset (0, 1)
    assert float(sim[5, 11]) == pytest.approx(across, abs=1e-6)  # the boundary pair
    assert float(sim[5, 3]) == 1.0
    z = midlevel_features(p, dtype=torch.float64).pca(3)  # 2 atoms: rank 1, zero padding
    assert torch.equal(z[0, 1:], torch.zeros_like(z[0, 1:]))
    assert float(z[0, 0, 5, 2]) * float(z[0, 0, 5, 25]) < 0


def test_uncovered_atoms_are_zero():
    labels = torch.tensor([[0, 0, 1], [1, 2, 2]])
    member = torch.tensor([[True, False], [True, True], [False, False]])
    p = Proposals(
        labels,
        member,
        torch.tensor([1.0, 0.5]),
        torch.zeros(2, 4, dtype=torch.long),
        torch.zeros(2, dtype=torch.long),
        (),
    )
    m = midlevel_features(p, dtype=torch.float64)
    assert m.covered.tolist() == [True, True, False]
    g = m.dense()[0]
    assert float(g[:, 1, 2].abs().sum()) == 0.0
    sim = m.similarity(Stencil.square(2, 3, 3))[0]
    assert float(sim[0, 1, 1]) == 0.0  # pair inside the uncovered atom
    assert float(sim[0, 0, 0]) == 1.0
    expected = 1.0 / np.sqrt(1.25)  # <(1, 0), (1, 0.5) / |(1, 0.5)|>
    assert float(sim[0, 0, 1]) == pytest.approx(expected)


def test_dtype_device_and_batch(props):
    like = torch.zeros(1, dtype=torch.float64)
    m64 = midlevel_features(props, like=like)
    assert m64.atom_g.dtype == torch.float64 and m64.pca(2).dtype == torch.float64
    m32 = midlevel_features(props)
    assert m32.atom_g.dtype == torch.float32
    st = Stencil.square(H, W, 3)
    torch.testing.assert_close(m32.similarity(st), m64.similarity(st).float(), rtol=0, atol=1e-6)
    batch = midlevel_features_batch([props, props], dtype=torch.float64)
    assert isinstance(batch, MidLevelBatch) and len(batch) == 2
    assert batch.pca(5).shape == (2, 5, H, W)
    sims = batch.similarity(st)
    assert sims.shape == (2, 4, H, W)
    torch.testing.assert_close(sims[1], m64.similarity(st)[0], rtol=0, atol=0)


def test_errors(props, mid):
    p = props.num_proposals
    with pytest.raises(ParameterError, match=rf"PCA dim must be an int in \[1, P = {p}\]"):
        mid.pca(p + 1)
    with pytest.raises(ParameterError, match="method must be"):
        mid.pca(2, "svd")
    with pytest.raises(ShapeError, match=f"stencil is 10x10 but the features are {H}x{W}"):
        mid.similarity(Stencil.square(10, 10, 3))
    with pytest.raises(ShapeError, match="expected Proposals, got Tensor"):
        midlevel_features(torch.zeros(3))
    with pytest.raises(ParameterError, match="floating dtype"):
        midlevel_features(props, dtype=torch.int64)
    small = selective_search(np.zeros((10, 12, 3)), scales=(10,))
    with pytest.raises(ShapeError, match="same \\(H, W\\)"):
        midlevel_features_batch([props, small])
    with pytest.raises(ShapeError, match="empty"):
        midlevel_features_batch([])
