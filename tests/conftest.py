"""Fixtures of the whole suite."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def torch_exp_on_two_threads():
    """One parallel ``exp`` before any test, on two threads.

    In a few processes of a hundred, torch's first parallel ``exp`` (torch 2.13.0 on the CPU,
    2 threads) comes out up to 1.5e-4 (relative) off on its second thread; every later call
    is exact. Several tests compare two ways of computing the same values bit for bit, so
    every test process makes that first call here, on two threads as the parallel kernel
    tests use.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(max(before, 2))
    torch.rand(1 << 17).exp_()
    torch.set_num_threads(before)
