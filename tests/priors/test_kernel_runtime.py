"""Where the compiled kernels apply, and their band pool."""

from __future__ import annotations

import pytest
import torch

from torchiid.priors import kernel_runtime
from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.stencil import Stencil

pytestmark = pytest.mark.skipif(kernel_runtime.compiled() is None, reason="needs numba")


def test_autograd_and_other_dtypes_keep_the_torch_ops():
    x = torch.rand(1, 1, 8, 8, requires_grad=True)
    w = torch.rand(1, 4, 8, 8)
    assert not kernel_runtime.usable(x, w)
    with torch.no_grad():
        assert kernel_runtime.usable(x, w)
    assert not kernel_runtime.usable(x.detach().half(), w.half())
    assert not kernel_runtime.usable(x.detach(), w.double())
    # the differentiable loss path still gets a gradient
    q = StencilQuadratic(Stencil.square(8, 8, 3), w)
    q.energy(x).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_environment_switch_turns_the_kernels_off(monkeypatch):
    monkeypatch.setenv("TORCHIID_KERNELS", "torch")
    kernel_runtime.compiled.cache_clear()
    try:
        assert not kernel_runtime.usable(torch.rand(1, 1, 4, 4))
    finally:
        monkeypatch.delenv("TORCHIID_KERNELS")
        kernel_runtime.compiled.cache_clear()
    assert kernel_runtime.usable(torch.rand(1, 1, 4, 4))


def test_an_unknown_switch_value_is_said_and_keeps_the_kernels(monkeypatch, caplog):
    monkeypatch.setenv("TORCHIID_KERNELS", "fast")
    kernel_runtime.compiled.cache_clear()
    try:
        with caplog.at_level("WARNING"):
            assert kernel_runtime.usable(torch.rand(1, 1, 4, 4))
    finally:
        monkeypatch.delenv("TORCHIID_KERNELS")
        kernel_runtime.compiled.cache_clear()
    assert "TORCHIID_KERNELS=fast is neither torch nor numba" in caplog.text


def test_a_forked_child_gets_its_own_band_pool(monkeypatch):
    import os

    first = kernel_runtime.executor(1)
    assert kernel_runtime.executor(1) is first
    pid = os.getpid()
    monkeypatch.setattr(kernel_runtime.os, "getpid", lambda: pid + 1)  # as in a fork's child
    second = kernel_runtime.executor(1)
    assert second is not first
    assert second.submit(lambda: 7).result() == 7
