import dataclasses
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.eval import mit_lmse
from torchiid.model import Decomposition, IntrinsicDecomposer, decompose
from torchiid.params import Parameters
from torchiid.synthetic import mondrian

# S_s on (lambda_s 0.01): the Mondrians' light is smooth everywhere, and the recovery bounds
# below were measured with it; the default leaves S_s off (it does not hold in cross-validation)
FAST = Parameters().replace(iterations=2, lambda_s=0.01)


def _spread(x):
    """Relative spread (std / mean) of a ratio: 0 when it is one constant scale."""
    return float(x.std() / x.mean())


def _corr(a, b):
    return float(torch.corrcoef(torch.stack([a.flatten(), b.flatten()]))[0, 1])


def _noisy_mondrian(seed, size=96):
    s = mondrian(size, size, seed=seed)
    g = torch.Generator().manual_seed(seed)
    noisy = (s.image * (1 + 0.05 * torch.randn(s.image.shape, generator=g))).clamp_min(0)
    return s, noisy


def test_layers_multiply_back_to_the_image():
    s = mondrian(64, 80, batch=2, seed=3)
    out = decompose(s.image, FAST, return_iterations=True)
    assert isinstance(out, Decomposition)
    assert out.reflectance.shape == (2, 3, 64, 80) and out.shading.shape == (2, 1, 64, 80)
    for i in range(2):
        # R and Stage 1's rho are the true reflectance up to a scale (measured: R / R_true
        # spreads 6-7%, I / R_true 24-33%); Stage 1's sigma follows the true shading
        assert _spread(out.reflectance[i] / s.reflectance[i]) < 0.15
        assert _spread(out.rho[i] / s.reflectance[i]) < 0.15
        assert _spread(out.reflectance[i] / s.reflectance[i]) < 0.4 * _spread(
            s.image[i] / s.reflectance[i]
        )
        assert _corr(out.sigma[i].log(), s.shading[i].log()) > 0.97
    assert len(out.iterations) == 2
    for layers in out.iterations:
        assert layers.sigma.shape == (2, 1, 64, 80) and layers.reflectance.shape == (2, 3, 64, 80)
    # convention: reflectance is an albedo in [0, 1] whose 99.9th percentile of the
    # brightest channel is 1; the shading's 99th percentile is reported as shading_white
    for i in range(2):
        peak = out.reflectance[i].amax(0).flatten()
        assert float(peak.max()) <= 1.0
        assert float(torch.quantile(peak, 0.999, interpolation="higher")) == pytest.approx(
            1.0, abs=1e-3
        )
        q = torch.quantile(out.shading[i].flatten(), 0.99)
        assert float(q) == pytest.approx(float(out.shading_white[i]), rel=1e-4)
        assert float(out.albedo_excess[i]) <= 0.001 + 1 / (64 * 80)
        for layers in out.iterations:
            assert float(layers.reflectance[i].max()) <= 1.0 and float(layers.rho[i].max()) <= 1.0
    assert {"shading 1", "reflectance 2", "total"} <= set(out.times)


@pytest.mark.parametrize("seed", [0, 1])
def test_full_method_beats_stage1_only_and_identity_on_noisy_mondrian(seed):
    # default preset with the paper's S_l (t_e 0), k = 3, measured (seeds 0-3): full
    # 0.0010-0.0018, Stage 1 only 0.0010-0.0022, R = I 0.0046-0.0115. With the default's t_e
    # (0.015) full and Stage 1 only score 20-40% worse (documentation, Method page), and
    # they tie on seeds 0 and 3 (full 0.00197 against 0.00193, 0.00135 against 0.00132):
    # these pixel-sharp synthetic edges have no mixed pixels for t_e to find, so it only
    # removes S_l's ties. The claim is about the paper's alternation, so S_p's base is the
    # paper's too (base_mix 1): the default's mixed base (0.5) makes both better on seeds 0-3
    # (full 0.00158 -> 0.00152, 0.00141 -> 0.00133, 0.00182 -> 0.00172, 0.00096 -> 0.00094)
    # but Stage 1 only more so, which then beats full on seeds 0 and 3 (0.00137 against
    # 0.00152). Below: the mixed base makes the full method better
    s, img = _noisy_mondrian(seed)
    p = Parameters.preset("default").replace(iterations=3, t_e=0.0, base_mix=1.0)

    def lmse(r, sh):
        return float(mit_lmse(s.reflectance, s.shading, r, sh))

    full = decompose(img, p)
    stage1 = decompose(img, p.variant("baseline1"))
    e_full = lmse(full.reflectance, full.shading)
    e_stage1 = lmse(stage1.reflectance, stage1.shading)
    e_identity = lmse(img, torch.ones_like(s.shading))
    assert e_full < e_stage1 < e_identity
    # the mixed matting base does not cost the full method on piecewise-constant albedo,
    # where the paper's base (the flat previous reflectance) is the right one
    mixed = decompose(img, p.replace(base_mix=Parameters().shading.base_mix))
    assert lmse(mixed.reflectance, mixed.shading) < e_full


def test_module_equals_function_and_batch_equals_single():
    s = mondrian(64, 64, batch=2, seed=5)
    out = decompose(s.image, FAST)
    mod = IntrinsicDecomposer(FAST)(s.image)
    assert torch.equal(out.reflectance, mod.reflectance)
    for i in range(2):
        single = decompose(s.image[i : i + 1], FAST)
        assert torch.allclose(out.reflectance[i : i + 1], single.reflectance, atol=1e-5)
        assert torch.allclose(out.shading[i : i + 1], single.shading, atol=1e-5)


def test_torch_compile_compiles_the_model_around_the_decomposer():
    """A model holding the decomposer compiles; the decomposition itself runs as it is."""

    class Relit(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.decomposer = IntrinsicDecomposer(FAST)
            self.gain = torch.nn.Parameter(torch.tensor(1.5))

        def forward(self, image):
            out = self.decomposer(image)
            return out.reflectance * (self.gain * out.shading)

    graphs = []

    def backend(gm, example_inputs):  # records what dynamo hands over, runs it eagerly
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    model, image = Relit(), mondrian(64, 64, seed=2).image
    eager = model(image)
    compiled = torch.compile(model, backend=backend)(image)
    assert torch.equal(compiled, eager)
    ops = [n.target for g in graphs for n in g.graph.nodes if n.op == "call_function"]
    assert ops, "nothing around the decomposer was compiled"
    assert len(ops) <= 4, f"the decomposition was traced: {len(ops)} operations"
    torch._dynamo.reset()


def test_float64_agrees_with_float32():
    s = mondrian(64, 64, seed=7)
    o32 = decompose(s.image, FAST)
    o64 = decompose(s.image.double(), FAST)
    assert o64.reflectance.dtype == torch.float64
    # measured max difference 1.1e-3 (float32 CG tolerances); 1e-2 leaves room
    assert float((o64.reflectance.float() - o32.reflectance).abs().max()) < 1e-2


def test_mask_restricts_every_prior():
    s = mondrian(72, 72, seed=2)
    mask = torch.zeros(1, 1, 72, 72, dtype=torch.bool)
    mask[..., 6:66, 4:68] = True
    out = decompose(s.image, FAST, mask=mask)
    assert float(out.reflectance[~mask.expand(1, 3, -1, -1)].abs().max()) == 0
    assert float(out.shading[~mask].abs().max()) == 0
    inside = mask.expand(1, 3, -1, -1)
    # inside, R is the true reflectance up to a scale (measured spread 7%; I / R_true 35%)
    assert _spread((out.reflectance / s.reflectance)[inside]) < 0.15
    # what lies outside the mask cannot change the result inside
    other = s.image.clone()
    other[~mask.expand(1, 3, -1, -1)] = torch.rand(
        int((~inside).sum()), generator=torch.Generator().manual_seed(1)
    )
    out2 = decompose(other, FAST, mask=mask)
    assert torch.allclose(out.reflectance, out2.reflectance, atol=1e-5)


def test_working_resolution_brings_layers_back_to_full_size():
    s = mondrian(96, 128, seed=4)
    p = FAST.replace(max_side=80)
    out = decompose(s.image, p)
    assert out.reflectance.shape == (1, 3, 96, 128) and out.shading.shape == (1, 1, 96, 128)
    # edge-aware: the shading stays smooth across reflectance edges (no reflectance leaks in)
    corr = torch.corrcoef(torch.stack([out.shading.log().flatten(), s.shading.log().flatten()]))
    assert float(corr[0, 1]) > 0.9


def test_working_resolution_below_patch_size_is_rejected():
    # 128x96 at 64 px is 64x48: the longer side must be 80 for 60 px on the shorter one
    with pytest.raises(ParameterError, match=r"working resolution 64x48 \(--max-side 64\) is "
                       r"smaller than the 60 px patches; --max-side 80 or more, or 0 for the "
                       r"full resolution \(max_side in Python\)$"):  # fmt: skip
        decompose(mondrian(96, 128).image, FAST.replace(max_side=64))


@pytest.mark.parametrize(("size", "max_side"), [((60, 60), 512), ((120, 120), 60)])
def test_an_image_of_one_patch_decomposes(size, max_side):
    # the smallest allowed working size holds one 60 px patch: S_c has no neighbour to tie it
    # to and is left out, the other priors decompose it
    s = mondrian(*size, seed=2)
    p = Parameters().replace(iterations=1, max_side=max_side)
    out = decompose(s.image, p)
    assert out.reflectance.shape == (1, 3, *size)
    rebuilt = out.reflectance * out.shading
    assert torch.allclose(rebuilt, s.image, atol=1e-4)
    assert bool(torch.isfinite(out.shading).all()) and float(out.shading.min()) > 0


def test_a_solve_whose_residual_overflowed_stops_the_decomposition():
    # many alternations scale the schedule's weights by tau^(k-1) until float32 overflows
    # (with tau 1.2, alternation 328 on a 64x64 image): a result from there is meaningless
    from types import SimpleNamespace

    from torchiid.model import _check_finite_solves

    ok = SimpleNamespace(stage="reflectance", alternation=3, residual=0.01)
    _check_finite_solves([ok], Parameters(), 3)  # finite: nothing to say
    bad = SimpleNamespace(stage="shading", alternation=3, residual=float("inf"))
    with pytest.raises(ParameterError, match=r"shading solve of alternation 3 diverged.*1\.44"):
        _check_finite_solves([ok, bad], Parameters(), 3)
    _check_finite_solves([bad], Parameters(), 4)  # an earlier alternation was checked then


def test_the_module_names_bad_params_when_it_is_made():
    with pytest.raises(ParameterError, match="params must be a torchiid.Parameters, got dict"):
        IntrinsicDecomposer({"iterations": 1})


def test_progress_is_reported():
    calls = []
    decompose(mondrian(64, 64).image, FAST, progress=lambda *a: calls.append(a))
    assert calls[0][0] == "features" and [c[1] for c in calls[1:]] == [1, 2]


@pytest.mark.parametrize(
    ("image", "kwargs", "error", "message"),
    [
        (torch.rand(1, 3, 40, 80), {}, ImageError, "at least 60 px"),
        (torch.full((1, 3, 64, 64), float("nan")), {}, ImageError, "NaN"),
        (torch.rand(1, 4, 64, 64), {}, ShapeError, r"expected image of shape \(B, 3, H, W\)"),
        (
            torch.rand(1, 3, 64, 64),
            {"mask": torch.ones(1, 1, 32, 32, dtype=torch.bool)},
            ShapeError,
            "mask",
        ),
        (
            torch.rand(1, 3, 64, 64),
            {"mask": torch.zeros(1, 1, 64, 64, dtype=torch.bool)},
            ShapeError,
            "empty",
        ),
        (torch.rand(1, 3, 64, 64), {"mask": np.ones((64, 64))}, ShapeError, "torch.Tensor"),
        (torch.rand(1, 3, 64, 64), {"progress": 5}, ParameterError, "progress must be a callable"),
    ],
)
def test_bad_input_gets_clear_errors(image, kwargs, error, message):
    with pytest.raises(error, match=message):
        decompose(image, FAST, **kwargs)


def test_shading_caps_first_and_warm_solves(monkeypatch):
    import torchiid.stages.shading as shading

    caps = []
    real = shading.pcg

    def spy(matvec, rhs, **kwargs):
        if rhs.shape[-1] == 64:  # the full-resolution solves, not the coarse levels
            caps.append(kwargs["max_iter"])
        return real(matvec, rhs, **kwargs)

    monkeypatch.setattr(shading, "pcg", spy)
    img = mondrian(64, 64, seed=1).image
    p = FAST.replace(iterations=3, cg_max_iter=40, warm_cg_max_iter=7)
    decompose(img, p)
    assert caps == [40, 7, 7]
    caps.clear()
    decompose(img, p.replace(warm_cg_max_iter=0))  # 0: the same cap everywhere
    assert caps == [40, 40, 40]


def test_colour_weights_option_changes_stage2():
    img = mondrian(64, 64, seed=4).image
    bi = decompose(img, FAST)
    wide = decompose(img, FAST.replace(colour_weights="wide"))
    assert FAST.reflectance.colour_weights == "bi"
    assert not torch.allclose(bi.reflectance, wide.reflectance, atol=1e-4)


def test_runs_under_inference_mode_like_no_grad():
    s = mondrian(64, 64, seed=2)
    ref = decompose(s.image, FAST)
    with torch.inference_mode():
        out = decompose(s.image, FAST)
    torch.testing.assert_close(out.reflectance, ref.reflectance)


def test_numeric_masks_mean_nonzero_inside_like_everywhere():
    s = mondrian(72, 72, seed=2)
    mask = torch.zeros(1, 1, 72, 72, dtype=torch.bool)
    mask[..., 6:66, 4:68] = True
    as_bool = decompose(s.image, FAST, mask=mask)
    as_float = decompose(s.image, FAST, mask=mask.float()[0, 0] * 0.7)  # (H, W), nonzero inside
    assert torch.equal(as_bool.reflectance, as_float.reflectance)


def test_every_solve_is_reported_with_its_convergence():
    img = mondrian(64, 64, seed=1).image
    capped = decompose(img, FAST.replace(cg_max_iter=5, warm_cg_max_iter=3))
    assert [(r.stage, r.alternation) for r in capped.solves] == [
        ("shading", 1),
        ("reflectance", 1),
        ("shading", 2),
        ("reflectance", 2),
    ]
    first, warm = capped.solves[0], capped.solves[2]
    assert (first.cap, warm.cap) == (5, 3) and first.iterations == 5 and not first.converged
    assert first.residual > first.tolerance and not capped.converged
    assert "stopped at its cap of 5" in str(first) and first.capped
    # a solve that stops short of its cap (a breakdown) is not reported as capped
    short = dataclasses.replace(first, iterations=2)
    assert not short.capped and "short of its tolerance before its cap of 5" in str(short)
    # generous caps: the shading solves reach their tolerance
    loose = decompose(img, FAST.replace(cg_max_iter=3000, warm_cg_max_iter=0, cg_tol=1e-3))
    for r in loose.solves:
        if r.stage == "shading":
            assert r.converged and r.residual <= 1e-3 and r.iterations < 3000


def _print_on_same_hue(h=96, w=128):
    """Dark strokes of the ground's own chromaticity (4x darker) under a smooth light."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    shade = 0.35 + 0.65 * (0.5 + 0.5 * torch.cos(2.2 * xx + 0.8 * yy))
    ground = torch.tensor([0.45, 0.75, 0.45]).view(3, 1)
    refl = ground.view(3, 1, 1).expand(3, h, w).clone()
    strokes = torch.zeros(h, w, dtype=torch.bool)
    for r0 in (20, 44, 68):
        for c0 in range(12, 116, 14):
            strokes[r0 : r0 + 14, c0 : c0 + 3] = True
            strokes[r0 : r0 + 3, c0 : c0 + 9] = True
    refl[:, strokes] = ground * 0.25
    return (refl * shade)[None], shade, strokes


def test_intensity_aware_retinex_keeps_print_out_of_the_shading():
    # the paper's near-binary chromaticity weights tie the print to its ground, so the whole
    # print (log 0.25 = -1.39) lands in the shading; t_i leaves it to the reflectance
    image, shade, strokes = _print_on_same_hue()
    base = Parameters().replace(
        iterations=2,
        patch_size=32,
        patch_stride=16,
        shading_preconditioner="multigrid",
        cg_max_iter=200,
        warm_cg_max_iter=0,
    )
    residue = {}
    for t_i in (0.0, 0.3):
        log_s = decompose(image, base.replace(t_i=t_i)).shading[0, 0].log()
        true = shade.log()
        residue[t_i] = float(
            (log_s[strokes].mean() - log_s[~strokes].mean())
            - (true[strokes].mean() - true[~strokes].mean())
        )
    assert residue[0.0] < -1.0
    assert abs(residue[0.3]) < 0.05


def _photo(h=96, w=128):
    from skimage import data

    from torchiid.core.colour import srgb_to_linear

    x = torch.from_numpy(data.chelsea()[::3, ::3][:h, :w].copy()).permute(2, 0, 1).float() / 255
    return srgb_to_linear(x)[None]


def test_converged_preset_converges_and_warns_only_when_a_cap_is_hit():
    import warnings

    from torchiid.core.exceptions import ConvergenceWarning

    p = Parameters.preset("converged").replace(iterations=2, patch_size=32, patch_stride=16)
    image = _photo()
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        out = decompose(image, p)  # no warning: every solve reached its tolerance
    assert out.converged and len(out.solves) == 4
    assert all(r.iterations < r.cap for r in out.solves)
    with pytest.warns(ConvergenceWarning, match="safety caps"):
        capped = decompose(image, p.replace(bregman_iter=2))
    assert not capped.converged
    # the default preset's caps are part of the method: reported, never warned about
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        assert not decompose(image, Parameters().replace(iterations=1)).converged


def test_print_preset_keeps_the_text_of_a_photographed_page_in_the_reflectance():
    # scikit-image's page: dark print on paper, unevenly lit. Print and paper have one
    # chromaticity, so the default's S_l ties them and the text goes to the shading (measured,
    # 1.13.0: ink/paper reflectance 0.929, shading 0.109, image 0.103); the print preset cuts
    # S_l on thin strokes (t_h) and keeps it in the reflectance (0.137 and 0.943; with every
    # alternation at full size 0.151 and 0.686)
    from scipy.ndimage import median_filter
    from skimage import data

    from torchiid.io import srgb_to_linear

    page = data.page().astype(np.float32) / 255
    ground = median_filter(page, size=15)
    ink, paper = page < 0.6 * ground, page > 0.95 * ground
    img = srgb_to_linear(torch.from_numpy(page)).expand(1, 3, *page.shape).contiguous()
    ratios = {}
    for preset in ("default", "print"):
        out = decompose(img, Parameters.preset(preset))
        r, s = out.reflectance[0].mean(0).numpy(), out.shading[0, 0].numpy()
        ratios[preset] = (r[ink].mean() / r[paper].mean(), s[ink].mean() / s[paper].mean())
    assert ratios["print"][0] < 0.3 and ratios["print"][1] > 0.5
    assert ratios["default"][0] > 2 * ratios["print"][0]


def test_the_public_names_stay_importable_from_torchiid_model():
    # the steps live in torchiid.pipeline; torchiid.model keeps the public names
    import torchiid.model as model

    names = {
        "Decomposition", "SolveReport", "FullLayers", "IterationLayers", "decompose",
        "full_resolution_layers", "IntrinsicDecomposer", "memory_needed",
        "BYTES_PER_WORKING_PIXEL", "BYTES_PER_FULL_PIXEL", "MEMORY_OVERHEAD",
        "MEMORY_CHECK_VARIABLE",
    }  # fmt: skip
    assert names <= set(model.__all__)
    assert all(getattr(model, name) is not None for name in names)


def test_the_solve_record_keeps_the_order_and_roundings_of_info_json():
    from torchiid.model import SolveReport
    from torchiid.pipeline.results import solve_record

    solves = (
        SolveReport("shading", 1, 40, 0, 1e-5, 1e-4, 100, True),
        SolveReport("reflectance", 1, 2, 6, 3e-2, 1e-3, 2, False),
    )
    result = Decomposition(
        torch.ones(2, 3, 4, 4), torch.ones(2, 1, 4, 4), None, None, (), FAST,
        albedo_excess=torch.tensor([0.25, 0.5]), solves=solves,
    )  # fmt: skip
    times = {"shading 1": 0.123456, "total": 1.0}
    record = solve_record(result, FAST, 2.34567, times, places=4)
    assert list(record) == [
        "albedo_quantile", "albedo_excess", "seconds", "times", "converged", "solves",
    ]  # fmt: skip
    assert record["albedo_quantile"] == FAST.output.albedo_quantile
    assert record["albedo_excess"] == 0.25 and record["seconds"] == 2.346
    assert record["times"] == {"shading 1": 0.1235, "total": 1.0}
    assert record["converged"] is False and record["solves"] == [str(s) for s in solves]
    assert "times" not in solve_record(result, FAST, 2.0)


def test_the_module_shows_and_saves_its_parameters(tmp_path):
    params = Parameters.preset("converged").replace(iterations=3)
    module = IntrinsicDecomposer(params)
    assert repr(module) == "IntrinsicDecomposer(preset='converged', iterations=3)"
    assert repr(IntrinsicDecomposer()) == "IntrinsicDecomposer(preset='default')"
    torch.save(module.state_dict(), tmp_path / "module.pt")
    loaded = IntrinsicDecomposer()
    loaded.load_state_dict(torch.load(tmp_path / "module.pt", weights_only=True))
    assert loaded.params == params
    with pytest.raises(ParameterError, match="not saved by an IntrinsicDecomposer"):
        loaded.load_state_dict({"_extra_state": {"weights": 1}})


def test_loading_the_method_does_not_load_torch_compilers_machinery():
    """dynamo costs a process over a second and 80 MB; only a compilation should load it."""
    code = "import sys, torchiid, torchiid.model; print('torch._dynamo' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(
    ("module", "first_use"),
    [
        # the colour features' conversion (kornia, 20 MB)
        (
            "kornia",
            "from torchiid.priors.affinity import lab_features as f; f(torch.rand(1, 3, 4, 4))",
        ),
        # selective search's colour spaces (OpenCV, 10 MB)
        (
            "cv2",
            "from torchiid.features.proposal_features import to_colour_space as f; "
            "f(numpy.full((4, 4, 3), 0.5), 'lab')",
        ),
    ],
)
def test_a_heavy_library_is_loaded_at_its_first_use_not_by_the_method(module, first_use):
    """Not resident yet while Stage 0's CNN pass sets one of a decomposition's peaks."""
    code = (
        "import sys, numpy, torch, torchiid, torchiid.model, torchiid.features\n"
        f"print({module!r} in sys.modules)\n"
        f"{first_use}\n"
        f"print({module!r} in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]
