import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.quadratic_term import QuadraticTerm, sparse_gram


class Scaled(QuadraticTerm):
    """``c ‖x‖²``: the smallest complete term."""

    def __init__(self, c):
        self.c = c
        self.shape, self.dtype, self.device = (1, 1, 2, 3), torch.float64, torch.device("cpu")

    def matvec(self, x):
        self._check(x)
        return self.c * x


def test_energy_and_the_default_right_hand_side():
    q = Scaled(2.0)
    x = torch.arange(6, dtype=torch.float64).view(1, 1, 2, 3)
    assert torch.equal(q.rhs(), torch.zeros(1, 1, 2, 3, dtype=torch.float64))
    torch.testing.assert_close(q.energy(x), 2.0 * (x**2).flatten(1).sum(1))
    with pytest.raises(ShapeError, match=r"expected x of shape \(1, 1, 2, 3\)"):
        q.matvec(x[..., :2])


def test_sparse_gram_is_dt_d():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(5, 4, generator=g, dtype=torch.float64)
    d[d.abs() < 0.5] = 0
    got = sparse_gram(d.to_sparse())
    assert got.is_sparse and got.is_coalesced()
    torch.testing.assert_close(got.to_dense(), d.T @ d)
