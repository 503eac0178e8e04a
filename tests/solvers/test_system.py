import scipy.sparse as sp
import torch
from test_stencil_operator import B, H, W, _rand, mixed_system

from torchiid.priors.matting import MattingQuadratic
from torchiid.priors.quadratic import SumQuadratic
from torchiid.solvers.amg import AMGPreconditioner
from torchiid.solvers.system import assemble_csr


def test_assembled_matrix_is_the_system():
    total = mixed_system()
    extra = _rand((B, 1, H, W), 4)
    mask = _rand((B, 1, H, W), 6) > 0.3
    dm = torch.diag(mask.reshape(-1).double())
    want = dm @ total.to_sparse().to_dense() @ dm + torch.diag(extra.reshape(-1))
    mat = assemble_csr(total, extra, mask)
    assert sp.issparse(mat) and mat.format == "csr"
    torch.testing.assert_close(torch.from_numpy(mat.toarray()), want)


def test_a_term_without_stencil_form_is_assembled_from_its_sparse_matrix():
    base = _rand((1, 3, 6, 7), 8)
    total = SumQuadratic([(1.0, MattingQuadratic(base, eps=1e-3))])
    extra = _rand((1, 1, 6, 7), 9)
    mask = _rand((1, 1, 6, 7), 10) > 0.2
    dm = torch.diag(mask.reshape(-1).double())
    want = dm @ total.to_sparse().to_dense() @ dm + torch.diag(extra.reshape(-1))
    got = torch.from_numpy(assemble_csr(total, extra, mask).toarray())
    torch.testing.assert_close(got, want)


def test_from_system_builds_from_the_assembly_and_times_it():
    total = mixed_system()
    extra = _rand((B, 1, H, W), 4) + 1.0
    m = AMGPreconditioner.from_system(total, extra, max_coarse=10)
    assert m.shape == (B, 1, H, W) and m.setup_time > 0
