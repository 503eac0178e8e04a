"""The methods an evaluation scores (``torchiid.eval.methods``)."""

import pytest
import torch

import torchiid.model as model
from torchiid.baselines import color_retinex
from torchiid.core.exceptions import ParameterError
from torchiid.eval import METHODS, method_parameters, run_method
from torchiid.params import Parameters


def test_each_method_runs_its_own_decomposition(monkeypatch):
    image = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0)) + 0.1
    out = run_method("r=i", image)
    assert torch.equal(out.reflectance, image) and torch.equal(out.shading, torch.ones(2, 1, 8, 8))
    out = run_method("s=i", image)
    assert torch.equal(out.shading, image.mean(1, keepdim=True))
    ref = color_retinex(image)
    out = run_method("retinex", image)
    assert torch.equal(out.reflectance, ref.reflectance) and torch.equal(out.shading, ref.shading)
    seen = []
    monkeypatch.setattr(model, "decompose", lambda *a, **k: seen.append((a, k)) or "done")
    params = Parameters().replace(iterations=1)
    assert run_method("semantic", image, None, params) == "done"
    assert seen[0][0][1] is params and seen[0][1] == {"mask": None}
    with pytest.raises(ParameterError, match="unknown method 'magic'; choose one of semantic"):
        run_method("magic", image)
    assert set(METHODS) == {"semantic", "retinex", "r=i", "s=i"}


def test_method_parameters_are_what_the_method_runs_with():
    assert method_parameters("retinex")["threshold_gray"] == 0.075
    assert "mask" not in method_parameters("retinex") and method_parameters("s=i") == {}
    assert method_parameters("semantic") == Parameters.preset("default").to_dict()
    params = Parameters().replace(iterations=2)
    assert method_parameters("semantic", params)["iterations"] == 2
