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
