"""The shading system built from the stage's parameter group: its terms, weights and switches."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.params import ShadingParameters
from torchiid.priors.lle import patch_rgb_features
from torchiid.priors.shading_terms import shading_stencil
from torchiid.stages.config import ShadingProblem
from torchiid.stages.shading_system import build_shading_system
from torchiid.synthetic import mondrian

#: the paper's shading weights (lambda_g = lambda_m = 0.02, lambda_l = 2), without S_s
PAPER = ShadingParameters(lambda_m=0.02, lambda_s=0.0)


def _shading_problem(h=20, w=18, batch=1, seed=0, stride=5):
    syn = mondrian(h, w, batch=batch, seed=seed, dtype=torch.float64)
    st = shading_stencil(h, w)
    g = torch.nn.functional.one_hot(syn.labels, 16).permute(0, 3, 1, 2).double()
    sim = (g.unsqueeze(2) * st.neighbours(g)).sum(1)
    ys, xs = torch.arange(stride // 2, h, stride), torch.arange(stride // 2, w, stride)
    ctr = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)
    feats = patch_rgb_features(syn.image, ctr, patch_size=stride)
    return ShadingProblem(syn.image, patch_centers=ctr, patch_features=feats, similarity=sim)


@pytest.mark.parametrize(
    ("weights", "drop", "names"),
    [
        ({}, (), ("S_c", "S_p", "S_m", "S_l")),
        ({"use_sc": False}, (), ("S_p", "S_m", "S_l")),
        ({"use_sp": False, "lambda_m": 0.0}, (), ("S_c", "S_l")),
        ({"lambda_g": 0.0}, (), ("S_m", "S_l")),
        ({"use_sl": False}, (), ("S_c", "S_p", "S_m")),
        ({"use_sp": False, "use_sm": False, "lambda_l": 0.0}, (), ("S_c",)),
        ({"lambda_s": 0.01}, (), ("S_c", "S_p", "S_m", "S_l", "S_s")),
        ({"lambda_s": 0.01, "stage1": False}, (), ()),
        # a prior without its tensors is off whatever its weight
        ({}, ("similarity",), ("S_c", "S_p", "S_l")),
        ({}, ("patch_centers", "patch_features"), ("S_p", "S_m", "S_l")),
        ({"use_sp": False}, ("patch_centers", "patch_features", "similarity"), ("S_l",)),
    ],
)
def test_shading_system_terms_and_their_weighted_sum(weights, drop, names):
    problem = _shading_problem(batch=2).replace(**{k: None for k in drop})
    shading = PAPER.replace(**weights)
    if not names:
        with pytest.raises(ParameterError, match="switched off"):
            build_shading_system(problem, shading)
        return
    system = build_shading_system(problem, shading)
    assert tuple(system.terms) == names
    assert set(system.times) == set(names)
    for name, (lam, _) in system.terms.items():
        field = {"S_c": "lambda_g", "S_p": "lambda_g", "S_m": "lambda_m", "S_l": "lambda_l"}
        assert lam == getattr(shading, field.get(name, "lambda_s")) > 0
    b, _, h, w = problem.image.shape
    x = torch.randn(b, 1, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref = sum(lam * term.matvec(x) for lam, term in system.terms.values())
    out = system.total.matvec(x)
    scale = float(ref.abs().max())
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-12 * scale)
    # the same for the diagonal and the right-hand side the solver uses
    torch.testing.assert_close(
        system.total.diagonal(),
        sum(lam * term.diagonal() for lam, term in system.terms.values()),
        rtol=1e-10,
        atol=1e-12 * scale,
    )
    torch.testing.assert_close(
        system.total.rhs(),
        sum(lam * term.rhs() for lam, term in system.terms.values()),
        rtol=1e-10,
        atol=1e-12 * scale,
    )


def test_shading_system_with_every_prior_off_raises():
    problem = _shading_problem()
    off = PAPER.replace(lambda_g=0.0, lambda_m=0.0, lambda_l=0.0)
    assert not off.active and not PAPER.replace(use_sl=False, lambda_g=0.0, use_sm=False).active
    with pytest.raises(ParameterError, match="switched off"):
        build_shading_system(problem, off)
