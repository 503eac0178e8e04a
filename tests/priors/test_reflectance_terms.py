import torch
from test_l1_terms import D, _stencil_term

from torchiid.priors.l1_terms import L1Term


def test_bregman_step_without_l1_gives_the_same_update():
    term = _stencil_term()
    g = torch.Generator().manual_seed(6)
    z = torch.rand(2, 3, 5, 6, generator=g, dtype=D)
    b0 = torch.randn(term.init_state(z).shape, generator=g, dtype=D) * 0.1 * term.stencil.valid
    b1, r1, l1 = term.bregman_step(z, b0.clone(), 0.05, with_l1=False)
    b2, r2, _ = term.bregman_step(z, b0.clone(), 0.05)
    assert l1 is None
    torch.testing.assert_close(b1, b2)
    torch.testing.assert_close(r1, r2)


def test_fused_bregman_step_matches_generic():
    term = _stencil_term()
    g = torch.Generator().manual_seed(5)
    z = torch.rand(2, 3, 5, 6, generator=g, dtype=D)
    b0 = torch.randn(term.init_state(z).shape, generator=g, dtype=D) * 0.1 * term.stencil.valid
    b1, r1, l1 = term.bregman_step(z, b0.clone(), 0.05)
    b2, r2, l2 = L1Term.bregman_step(term, z, b0.clone(), 0.05)
    torch.testing.assert_close(b1, b2)
    torch.testing.assert_close(r1, r2)
    torch.testing.assert_close(l1, l2)
    assert b1.abs().max() <= 0.05 + 1e-12
