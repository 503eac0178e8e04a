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
def torch_exp_on_every_thread():
    """torch's ``exp`` run once on all its threads before any kernel test, as the pipeline does.

    In a fresh process whose first parallel ``exp`` comes right after a compiled kernel wrote
    its input, the part on torch's second thread was seen to be off by up to 1.5e-4 (relative)
    in a few processes of a hundred; every later call is exact. The pipeline's own torch ops
    run before its first kernel, so its results are the same in every process; the tests that
    compare the kernels with the torch ops bit for bit start from that state too.
    """
    torch.rand(1 << 17).exp_()
