import pytest
import torch

from torchiid.features.onnx_backend import ensure_onnx_model


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Tiny inputs: one thread avoids OpenMP oversubscription on a busy 2-core machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def onnx_path(tmp_path_factory):
    """One ONNX export per test session, in a temporary cache (the manifest makes it reused)."""
    return ensure_onnx_model(tmp_path_factory.getbasetemp() / "torchiid-onnx")
