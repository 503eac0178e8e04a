"""Fixtures of the compiled kernels' tests: both thread layouts, and the torch reference."""

from __future__ import annotations

import pytest
import torch

from torchiid.priors import kernel_runtime, kernels


@pytest.fixture(params=["serial", "parallel"])
def kernel_variant(request, monkeypatch):
    """Every test runs on the calling thread alone, and in row bands on 2 threads."""
    if request.param == "parallel":
        monkeypatch.setattr(kernel_runtime, "PARALLEL_WORK", 0)
        before = torch.get_num_threads()
        torch.set_num_threads(2)
        yield request.param
        torch.set_num_threads(before)
    else:
        monkeypatch.setattr(kernel_runtime, "PARALLEL_WORK", float("inf"))
        yield request.param


@pytest.fixture
def torch_ops(monkeypatch):
    """Run the block with the torch ops (the reference), as ``TORCHIID_KERNELS=torch`` does."""

    def run(fn):
        with monkeypatch.context() as m:
            m.setattr(kernels, "usable", lambda *t, **k: False)
            return fn()

    return run


@pytest.fixture(scope="session", autouse=True)
def torch_exp_on_two_threads():
    """One parallel ``exp`` before the kernel tests, on two threads.

    In up to about one process in ten, torch's first parallel ``exp`` (torch 2.13.0 on the CPU,
    2 threads) comes out up to 1.5e-4 (relative) off on its second thread; every later call
    is exact. These tests compare the kernels with the torch ops, and two ways of computing
    the same weights bit for bit, so their process makes that first call here, on two threads
    as the parallel kernel tests use.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(max(before, 2))
    torch.rand(1 << 17).exp_()
    torch.set_num_threads(before)
