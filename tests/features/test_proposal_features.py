"""torchiid.features.proposal_features: the colour and texture histograms of the atoms."""

import numpy as np
import pytest
from skimage import data, transform

from torchiid.features.proposal_features import atom_histograms


@pytest.fixture(scope="module")
def astronaut():
    return transform.resize(data.astronaut(), (48, 64), anti_aliasing=True)  # sRGB floats


def test_atom_histograms(astronaut):
    rng = np.random.default_rng(0)
    atoms = rng.integers(0, 5, astronaut.shape[0] * astronaut.shape[1])
    hist = atom_histograms(astronaut, atoms, 5)
    sizes = np.bincount(atoms, minlength=5)
    assert hist.shape == (5, 75 + 240)
    per_group = np.concatenate(
        [hist[:, :75].reshape(5, 3, 25).sum(2), hist[:, 75:].reshape(5, 24, 10).sum(2)], 1
    )
    np.testing.assert_array_equal(per_group, np.repeat(sizes[:, None], 27, 1))
    for c in range(3):  # colour bins against numpy's histogram
        ref, _ = np.histogram(astronaut[..., c].reshape(-1)[atoms == 2], bins=25, range=(0, 1))
        np.testing.assert_array_equal(hist[2, c * 25 : (c + 1) * 25], ref)


@pytest.mark.parametrize("space", ["lab", "hsv"])
def test_compiled_atom_histograms_count_as_the_numpy_path(astronaut, space, monkeypatch):
    from torchiid.features import proposal_features as pf

    if pf._kernels() is None:
        pytest.skip("needs numba")
    x = pf.to_colour_space(astronaut, space)
    atoms = np.random.default_rng(1).integers(0, 40, x.shape[0] * x.shape[1])
    fast = atom_histograms(x, atoms, 40)
    with monkeypatch.context() as m:
        m.setattr(pf, "_kernels", lambda: None)
        ref = atom_histograms(x, atoms, 40)
    assert fast.sum() == ref.sum() == x.shape[0] * x.shape[1] * 27
    np.testing.assert_array_equal(fast, ref)
