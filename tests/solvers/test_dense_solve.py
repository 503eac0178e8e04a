import torch

from torchiid.solvers.dense import DenseSPD


def test_solves_spd_systems_and_stays_spd_where_round_off_made_one_indefinite():
    g = torch.Generator().manual_seed(0)
    q, _ = torch.linalg.qr(torch.randn(2, 6, 6, generator=g, dtype=torch.float64))
    ev = torch.tensor([[1.0, 2, 3, 4, 5, 6], [-1e-9, 1e-3, 1, 2, 3, 4]], dtype=torch.float64)
    mats = q @ torch.diag_embed(ev) @ q.transpose(1, 2)
    rhs = torch.randn(1, 6, 3, generator=g, dtype=torch.float64)
    spd = DenseSPD(mats[:1].float())  # a float32 input is solved in float64
    assert spd.eig is None and spd.solve(rhs).dtype == torch.float64
    torch.testing.assert_close(spd.solve(rhs), torch.linalg.solve(mats[:1], rhs), rtol=1e-5,
                               atol=1e-5)  # fmt: skip
    clipped = DenseSPD(mats[1:])
    assert clipped.eig is not None
    x = torch.randn(1, 6, 1, generator=g, dtype=torch.float64)
    assert float((x.transpose(1, 2) @ clipped.solve(x)).squeeze()) > 0
    # the rest of the spectrum is solved exactly: the eigenvector of 1 keeps its energy
    v = q[1:, :, 2:3]
    torch.testing.assert_close(float((v.transpose(1, 2) @ clipped.solve(v)).squeeze()), 1.0)
