"""The priors as differentiable losses (``torchiid.losses``)."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.losses import (
    PriorLoss,
    image_priors,
    reconstruction_loss,
    reflectance_losses,
    shading_losses,
)
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.synthetic import mondrian

PARAMS = Parameters().replace(patch_size=8, patch_stride=4, lambda_s=0.01)  # S_s on too


def test_gradcheck_float64_tiny():
    img = mondrian(8, 8, dtype=torch.float64).image
    params = PARAMS.replace(use_sc=False)  # one 8 px patch: no LLE neighbours
    loss = PriorLoss(params)
    priors = loss.priors(img)
    assert set(priors.shading) == {"S_p", "S_m", "S_l", "S_s"}
    g = torch.Generator().manual_seed(0)
    refl = (0.2 + 0.6 * torch.rand(1, 3, 8, 8, dtype=torch.float64, generator=g)).requires_grad_()
    shad = (0.3 + torch.rand(1, 1, 8, 8, dtype=torch.float64, generator=g)).requires_grad_()
    # fast mode: the analytic and numerical Jacobians compared along random directions
    assert torch.autograd.gradcheck(
        lambda r, s: loss(img, r, s, priors), (refl, shad), fast_mode=True
    )
    # in log space as well
    log_loss = PriorLoss(params, log_space=True)
    lr, ls = refl.detach().log().requires_grad_(), shad.detach().log().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda r, s: log_loss(img, r, s, priors), (lr, ls), fast_mode=True
    )


def test_the_image_weights_carry_no_gradient():
    img = mondrian(12, 12, dtype=torch.float64).image.requires_grad_()
    pr = image_priors(img, PARAMS)
    for p in pr.shading.values():
        assert not p.matvec(torch.ones(1, 1, 12, 12, dtype=torch.float64)).requires_grad
    for p in pr.reflectance.values():
        assert not p.apply(torch.ones(1, 3, 12, 12, dtype=torch.float64)).requires_grad


def test_components_and_dtype():
    m = mondrian(16, 16, batch=2)  # float32
    loss = PriorLoss(PARAMS)
    pr = loss.priors(m.image)
    parts = loss.components(m.image, m.reflectance, m.shading, pr)
    assert set(parts) == {"reconstruction", "S_c", "S_p", "S_m", "S_l", "S_s", "A", "B", "C"}
    assert all(v.shape == (2,) and v.dtype == torch.float32 for v in parts.values())
    total = loss(m.image, m.reflectance, m.shading, pr)
    torch.testing.assert_close(total, torch.stack(list(parts.values())).sum(0).mean())
    # the unweighted pieces
    assert set(shading_losses(m.shading.log(), pr.shading)) == {"S_c", "S_p", "S_m", "S_l", "S_s"}
    assert set(reflectance_losses(m.reflectance, pr.reflectance)) == {"A", "B", "C"}
    # a reflectance 10% too bright leaves 0.1·I per pixel: the loss is Σ (0.1·I)², per image
    brighter = m.reflectance * 1.1
    want = (0.1 * m.image).square().flatten(1).sum(1)
    torch.testing.assert_close(reconstruction_loss(m.image, brighter, m.shading), want)
    top = torch.zeros(2, 1, 16, 16, dtype=torch.bool)
    top[..., :8, :] = True
    want_top = (0.1 * m.image[..., :8, :]).square().flatten(1).sum(1)
    torch.testing.assert_close(reconstruction_loss(m.image, brighter, m.shading, top), want_top)
    only_rec = PriorLoss(PARAMS, use_shading=False, use_reflectance=False)
    assert set(only_rec.components(m.image, m.reflectance, m.shading)) == {"reconstruction"}


def test_the_methods_decomposition_beats_r_equals_i():
    img = mondrian(32, 32, dtype=torch.float64).image
    params = PARAMS.replace(iterations=2)
    out = decompose(img, params)
    loss = PriorLoss(params)
    pr = loss.priors(img)
    method = loss(img, out.reflectance, out.shading, pr)
    trivial = loss(img, img, torch.ones_like(out.shading), pr)
    assert float(method) < float(trivial)
    # the method's reflectance lost the shading's gradients: its L1 terms are far lower
    parts = loss.components(img, out.reflectance, out.shading, pr)
    flat = loss.components(img, img, torch.ones_like(out.shading), pr)
    for name in ("A", "B"):
        assert float(parts[name]) < 0.5 * float(flat[name]), name


def test_the_priors_take_what_decompose_takes_and_refuse_the_rest_clearly():
    m = mondrian(16, 16)
    unbatched = image_priors(m.image[0], PARAMS)
    assert unbatched.shape == (1, 16, 16) and unbatched.dtype == torch.float32
    for half in (torch.float16, torch.bfloat16):
        assert image_priors(m.image.to(half), PARAMS).dtype == torch.float32
    with pytest.raises(ShapeError, match=r"image"):
        image_priors(m.image.permute(0, 2, 3, 1), PARAMS)  # channels last: (1, H, W, 3)
    with pytest.raises(ShapeError, match="expected image to be a torch.Tensor"):
        image_priors(m.image[0].permute(1, 2, 0).numpy(), PARAMS)


def test_the_loss_of_mixed_precision_layers_is_taken_in_the_priors_dtype():
    m = mondrian(16, 16, batch=2)
    loss = PriorLoss(PARAMS)
    pr = loss.priors(m.image)
    want = loss(m.image, m.reflectance, m.shading, pr)
    for half in (torch.float16, torch.bfloat16):
        r = m.reflectance.to(half).requires_grad_()
        got = loss(m.image.to(half), r, m.shading.to(half), pr)
        assert got.dtype == torch.float32 and torch.isfinite(got)
        torch.testing.assert_close(got, want, rtol=0.05, atol=0)
        got.backward()
        assert r.grad is not None and r.grad.dtype == half and torch.isfinite(r.grad).all()


def test_layers_of_another_size_than_the_priors_are_a_shape_error():
    m = mondrian(16, 16)
    loss = PriorLoss(PARAMS)
    pr = loss.priors(m.image)
    crop = (m.image[..., :12, :12], m.reflectance[..., :12, :12], m.shading[..., :12, :12])
    with pytest.raises(ShapeError, match=r"the priors are of 1 image\(s\) of 16x16 px"):
        loss(*crop, pr)
    with pytest.raises(ShapeError, match="shading has shape"):
        loss(m.image, m.reflectance, m.shading[..., :12, :12], pr)


@pytest.fixture
def fresh_dynamo():
    """dynamo's caches empty before and after the test, whatever the test does."""
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


# dynamo reads the .grad of the network's outputs (not leaves) as it hands them to the eager
# loss; torch's warning about that is an error under this suite's filter
@pytest.mark.filterwarnings("ignore:The .grad attribute of a Tensor that is not a leaf")
def test_torch_compile_compiles_the_network_around_the_loss(fresh_dynamo):
    """A training step compiles the network; the loss runs as it is and its gradient arrives."""

    class Step(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Conv2d(3, 4, 3, padding=1)  # log R (3) and log S (1)
            self.loss = PriorLoss(PARAMS, log_space=True)

        def forward(self, image, priors):
            out = self.net(image.log())
            return self.loss(image, out[:, :3], out[:, 3:], priors)

    graphs = []

    def backend(gm, example_inputs):  # records what dynamo hands over, runs it eagerly
        graphs.append(gm)
        return gm.forward

    torch.manual_seed(0)
    step, image = Step(), mondrian(24, 24, seed=3).image
    priors = step.loss.priors(image)
    eager = step(image, priors)
    eager.backward()
    grads = [p.grad.clone() for p in step.net.parameters()]
    step.zero_grad()
    compiled = torch.compile(step, backend=backend)(image, priors)
    compiled.backward()
    assert torch.equal(compiled, eager)
    for p, g in zip(step.net.parameters(), grads, strict=True):
        assert torch.equal(p.grad, g)
    ops = [n.target for g in graphs for n in g.graph.nodes if n.op == "call_function"]
    assert torch.conv2d in ops, "the network was not compiled"
    assert len(ops) <= 6, f"the loss was traced: {len(ops)} operations"
    # the terms one by one, too
    graphs.clear()
    r, s = image.log(), torch.zeros_like(image[:, :1])
    terms = torch.compile(step.loss.components, backend=backend)(image, r, s, priors)
    assert terms.keys() == step.loss.components(image, r, s, priors).keys()
    assert not [n for g in graphs for n in g.graph.nodes if n.op == "call_function"]
    # and the priors
    built = torch.compile(step.loss.priors, backend=backend)(image)
    assert built.shading.keys() == priors.shading.keys()
    for name, prior in built.shading.items():
        assert torch.equal(prior.matvec(s), priors.shading[name].matvec(s))
    assert not [n for g in graphs for n in g.graph.nodes if n.op == "call_function"]
