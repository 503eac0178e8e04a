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


@pytest.fixture
def one_thread():
    """One torch thread for a bitwise comparison of two runs of the same edit.

    Element-wise kernels split a tensor among the threads they get, and an element's value can
    differ in its last bit between the vectorised body of a chunk and its scalar tail; a busy
    machine can hand the two runs different numbers of threads.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
