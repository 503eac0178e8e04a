"""A synthetic scene with known layers and a rectangular region, for the edit tests."""

import pytest
import torch

from torchiid.synthetic import mondrian


@pytest.fixture(scope="module")
def scene():
    return mondrian(48, 64, seed=3, dtype=torch.float64)


@pytest.fixture
def box():
    """``(1, 1, 48, 64)`` bool: rows 10-29, columns 16-43."""
    m = torch.zeros(1, 1, 48, 64, dtype=torch.bool)
    m[..., 10:30, 16:44] = True
    return m
