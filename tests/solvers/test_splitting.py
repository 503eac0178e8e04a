import pytest
import torch
from test_split_bregman import _gap_problem

from torchiid.solvers.splitting import change_penalty


@pytest.mark.parametrize("fixed", [False, True], ids=["float32", "int16"])
def test_a_change_of_penalty_keeps_the_multipliers_and_the_next_right_hand_side(fixed):
    # after b' = clamp(W M z + b) at θ, moving to θ' must leave the z step's right-hand side
    # equal to its definition 2γ_a ρ + θ' Σ (W M)ᵀ (d − b θ/θ'), d = W M z + b − b'
    storage = torch.empty(1, 3, 12, 14, 15, dtype=torch.int16) if fixed else None
    rho, terms, gam = _gap_problem(dtype=torch.float32, state=storage)
    assert terms[0].stencil.num_offsets == 12
    g = torch.Generator().manual_seed(9)
    z = torch.rand(rho.shape, generator=g)
    ga, theta, theta2 = 1.0, 2.0, 0.5
    lams = [gg / theta for gg in gam]
    new_lams = [gg / theta2 for gg in gam]
    # states after a first update, then the measured second update
    states = [t.bregman_step(torch.rand(rho.shape, generator=g), None, lam, False)[0]
              for t, lam in zip(terms, lams, strict=True)]  # fmt: skip

    def decoded(n):
        b = states[n]
        return b.float() * terms[0].state_step if b.dtype == torch.int16 else b.clone()

    before = [decoded(n) for n in range(2)]
    rhs = 2 * ga * rho
    adjoint = torch.zeros_like(rho)
    for n, (t, lam) in enumerate(zip(terms, lams, strict=True)):
        states[n], r, _, m = t.bregman_step(z, states[n], lam, False, stats=True)
        rhs += theta * r
        adjoint += theta * m.adjoint
    after = [decoded(n) for n in range(2)]
    active = list(zip(terms, gam, strict=True))
    new = change_penalty(rhs.clone(), 2 * ga * rho, adjoint, states, active, lams, new_lams, 0.25)
    expect = 2 * ga * rho
    for n, t in enumerate(terms):
        rescaled = decoded(n)
        valid = torch.isfinite(rescaled) & (after[n].abs() <= lams[n] * 1.0001)
        scaled = torch.where(valid, after[n] * theta / theta2, 0.0)
        assert torch.allclose(torch.where(valid, rescaled, 0.0), scaled, atol=new_lams[n] / 30000)
        wz = t.apply(z)
        d = wz + torch.where(valid, before[n], 0.0) - torch.where(valid, after[n], 0.0)
        expect = expect + theta2 * t.adjoint(torch.where(valid, d, 0.0) - scaled)
    assert torch.allclose(new, expect, atol=2e-3 * float(expect.abs().max()))
