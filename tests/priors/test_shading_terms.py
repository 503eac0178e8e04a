import math

import pytest
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.priors.shading_terms import (
    edge_confidence,
    midlevel_term,
    retinex_term,
    retinex_weights,
    shading_stencil,
    smoothness_term,
)

NBRS = [(0, 1), (1, -1), (1, 0), (1, 1)]


def _pairs(h, w):
    for y in range(h):
        for x in range(w):
            for dy, dx in NBRS:
                if 0 <= y + dy < h and 0 <= x + dx < w:
                    yield y, x, y + dy, x + dx


def _dense_from_pairs(h, w, weight_fn, target_fn=None):
    n = h * w
    a = torch.zeros(n, n, dtype=torch.float64)
    bvec = torch.zeros(n, dtype=torch.float64)
    for y, x, yy, xx in _pairs(h, w):
        i, j = y * w + x, yy * w + xx
        wij = weight_fn(y, x, yy, xx)
        a[i, i] += wij
        a[j, j] += wij
        a[i, j] -= wij
        a[j, i] -= wij
        if target_fn is not None:
            c = target_fn(y, x, yy, xx)
            bvec[i] += wij * c
            bvec[j] -= wij * c
    return a, bvec


def test_midlevel_matches_dense():
    torch.manual_seed(0)
    h, w = 6, 7
    g = torch.randn(1, 5, h, w, dtype=torch.float64)
    g[:, :, :, 4:] = g[:, :, :1, :1]  # a uniform region: similarity 1
    g = g / g.norm(dim=1, keepdim=True)
    st = shading_stencil(h, w)
    sim = (g.unsqueeze(2) * st.neighbours(g)).sum(1)
    term = midlevel_term(sim, st, t_m=0.5)

    def wfn(y, x, yy, xx):
        dot = float((g[0, :, y, x] * g[0, :, yy, xx]).sum())
        return math.exp(-((1 - dot) ** 2) / 0.25)

    a, _ = _dense_from_pairs(h, w, wfn)
    torch.testing.assert_close(term.to_sparse().to_dense(), a)
    x = torch.randn(1, 1, h, w, dtype=torch.float64)
    torch.testing.assert_close(term.matvec(x).reshape(-1), a @ x.reshape(-1))
    torch.testing.assert_close(term.diagonal().reshape(-1), a.diagonal())


def test_smoothness_matches_dense_8_neighbour_laplacian():
    h, w = 5, 6
    st = shading_stencil(h, w)
    term = smoothness_term(st, 2, dtype=torch.float64)
    a, _ = _dense_from_pairs(h, w, lambda *_: 1.0)
    dense = term.to_sparse().to_dense()
    torch.testing.assert_close(dense[: h * w, : h * w], a)
    torch.testing.assert_close(dense[h * w :, h * w :], a)
    assert float(dense[: h * w, h * w :].abs().max()) == 0.0  # images are independent
    # an interior pixel has 8 neighbours, a corner 3
    assert float(a[w + 1, w + 1]) == 8.0 and float(a[0, 0]) == 3.0
    x = torch.randn(2, 1, h, w, dtype=torch.float64)
    torch.testing.assert_close(term.matvec(x).reshape(-1), dense @ x.reshape(-1))
    ones = torch.ones(2, 1, h, w, dtype=torch.float64)
    assert float(term.matvec(ones).abs().max()) < 1e-12
    with pytest.raises(ParameterError, match="batch"):
        smoothness_term(st, 0)


def test_retinex_matches_dense_and_formula():
    torch.manual_seed(1)
    h, w = 5, 6
    img = torch.rand(1, 3, h, w, dtype=torch.float64) * 0.2
    img[:, :, 2:, :3] = torch.tensor([0.02, 0.03, 0.04], dtype=torch.float64).view(1, 3, 1, 1)
    img[:, :, :2, :] = img[:, :, :1, :1] * torch.linspace(0.5, 2, w, dtype=torch.float64)
    st = shading_stencil(h, w)
    tc, tb = 0.05, 0.05
    term = retinex_term(img, st, t_c=tc, t_b=tb)
    p = img.mean(1)[0]
    chrom = img[0] / img[0].norm(dim=0, keepdim=True)

    def wfn(y, x, yy, xx):
        cos = float((chrom[:, y, x] * chrom[:, yy, xx]).sum())
        dark = 1 + math.exp(-(float(p[y, x]) ** 2 + float(p[yy, xx]) ** 2) / tb**2)
        return math.exp(-((1 - cos) ** 2) / tc**2) * dark

    def cfn(y, x, yy, xx):
        return math.log(float(p[y, x])) - math.log(float(p[yy, xx]))

    a, bvec = _dense_from_pairs(h, w, wfn, cfn)
    torch.testing.assert_close(term.to_sparse().to_dense(), a)
    torch.testing.assert_close(term.rhs().reshape(-1), bvec)
    # energy at s equals the literal Eq. 5 sum up to a constant: check the difference of two s
    s1, s2 = torch.randn(2, 1, 1, h, w, dtype=torch.float64)
    logp = p.log()

    def eq5(s):
        tot = 0.0
        for y, x, yy, xx in _pairs(h, w):
            r = (logp[y, x] - s[0, 0, y, x]) - (logp[yy, xx] - s[0, 0, yy, xx])
            tot += wfn(y, x, yy, xx) * float(r) ** 2
        return tot

    got = float(term.energy(s1)[0] - term.energy(s2)[0])
    assert got == pytest.approx(eq5(s1) - eq5(s2), rel=1e-9)
    # the same-chromaticity pixels of the top rows are tied with weight ~1 (x 1-2 dark factor)
    wts = retinex_weights(img, st, tc, tb)
    assert float(wts[0, 0, 0, :-1].min()) > 0.99


def test_paper_tc_is_nearly_binary():
    img = torch.tensor([0.5, 0.5, 0.5]).view(1, 3, 1, 1).repeat(1, 1, 3, 3)
    img[0, :, :, 2] = torch.tensor([0.5, 0.525, 0.5]).view(3, 1)  # ~1.3 degrees away
    w = retinex_weights(img, shading_stencil(3, 3), t_c=1e-4, t_b=0.05)
    assert float(w[0, 0, 0, 0]) > 0.99  # identical colours
    assert float(w[0, 0, 0, 1]) < 0.01  # a 5% change in one channel: cut


def test_mask_zeroes_pairs_leaving_it():
    torch.manual_seed(2)
    img = torch.rand(1, 3, 5, 5)
    mask = torch.ones(1, 1, 5, 5, dtype=torch.bool)
    mask[0, 0, 2, 2] = False
    st = shading_stencil(5, 5)
    for term in (
        retinex_term(img, st, t_c=1.0, mask=mask),
        midlevel_term(torch.ones(1, 4, 5, 5), st, mask=mask),
        smoothness_term(st, 1, mask=mask),
    ):
        a = term.to_sparse().to_dense()
        assert float(a[12].abs().max()) == 0.0
        assert float(a.abs().sum()) > 0


def test_errors():
    st = shading_stencil(5, 5)
    with pytest.raises(ShapeError, match="similarity"):
        midlevel_term(torch.ones(1, 8, 5, 5), st)
    with pytest.raises(ParameterError):
        midlevel_term(torch.ones(1, 4, 5, 5), st, t_m=0)
    bad = torch.rand(1, 3, 5, 5)
    bad[0, 1, 1, 1] = float("nan")
    with pytest.raises(ImageError, match="NaN"):
        retinex_term(bad, st)
    with pytest.raises(ShapeError):
        retinex_term(torch.rand(1, 3, 6, 5), st)
    with pytest.raises(ShapeError, match="mask"):
        retinex_term(torch.rand(1, 3, 5, 5), st, mask=torch.ones(1, 1, 4, 5, dtype=torch.bool))


def test_intensity_factor_cuts_same_hue_edges_only():
    # three columns of one chromaticity: 0.6, 0.57 (a 5% shading step) and 0.15 (dark print)
    img = torch.tensor([0.6, 0.4, 0.2]).view(1, 3, 1, 1).repeat(1, 1, 3, 3)
    img[0, :, :, 1] *= 0.95
    img[0, :, :, 2] *= 0.25
    st = shading_stencil(3, 3)
    off = retinex_weights(img, st, t_c=1e-4, t_b=0.05)
    on = retinex_weights(img, st, t_c=1e-4, t_b=0.05, t_i=0.3)
    # (0, 1) neighbours: column 0 -> 1 keeps its weight, column 1 -> 2 (print edge) is cut
    assert float(on[0, 0, 0, 0]) == pytest.approx(
        float(off[0, 0, 0, 0]) * math.exp(-(math.log(0.95) ** 2) / 0.09), rel=1e-4
    )
    assert float(on[0, 0, 0, 0]) > 0.97 * float(off[0, 0, 0, 0])
    assert float(off[0, 0, 0, 1]) > 0.99
    assert float(on[0, 0, 0, 1]) < 1e-3
    with pytest.raises(ParameterError, match="t_i"):
        retinex_weights(img, st, t_i=-1.0)


def test_edge_confidence_marks_the_pixels_beside_a_colour_edge():
    # green | cream: the columns on either side of the edge are marked, the rest are not;
    # a brightness step of one colour is not a colour edge
    img = torch.empty(1, 3, 4, 8)
    img[..., :4] = torch.tensor([0.1, 0.3, 0.1]).view(3, 1, 1)
    img[..., 4:] = torch.tensor([0.8, 0.75, 0.55]).view(3, 1, 1)
    img[..., 6:] *= 0.3
    e = edge_confidence(img, 0.015)[0, 0]
    assert torch.all(e[:, 3:5] < 1e-6)
    assert torch.all(e[:, [0, 1, 2, 5, 6, 7]] == 1)
    # neighbours outside the mask do not count (the outside of a masked object is black)
    mask = torch.ones(1, 1, 4, 8, dtype=torch.bool)
    mask[..., :4] = False
    inside = edge_confidence(img * mask, 0.015, mask=mask)[0, 0]
    assert torch.all(inside[:, 4:] == 1)
    assert float(edge_confidence(img * mask, 0.015)[0, 0, 0, 4]) < 0.6  # black vs cream
    # S_l's pairs touching a marked pixel lose their weight
    st = shading_stencil(4, 8)
    off = retinex_weights(img, st)
    on = retinex_weights(img, st, t_e=0.015)
    right = [0, 2, 3]  # offsets (0, 1), (1, 0), (1, 1): from column 5 on, away from the edge
    assert torch.equal(on[:, right, :, 5:], off[:, right, :, 5:]) and float(off[0, 0, 1, 5]) > 0.99
    # pairs (1, 4)-(1, 5) and (1, 2)-(1, 3), one colour each, touch a marked pixel
    assert float(on[0, 0, 1, 4]) < 1e-12 and float(on[0, 0, 1, 2]) < 1e-12
    assert float(off[0, 0, 1, 4]) > 0.99 and float(off[0, 0, 1, 2]) > 0.99
    with pytest.raises(ParameterError, match="t_e"):
        edge_confidence(img, 0.0)
    with pytest.raises(ParameterError, match="t_e"):
        retinex_weights(img, st, t_e=-1.0)


def _edge_reference(img, t_e, t_d, mask):
    """``e_i = max_j d_ij`` over the 8 neighbours ``j`` in the image (and the mask), by loops."""
    _, _, h, w = img.shape
    p = img[0].clamp_min(1e-4)
    chrom = p / p.norm(dim=0, keepdim=True)
    logp = p.mean(0).log()
    e = torch.zeros(h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = y + dy, x + dx
                    if (dy, dx) == (0, 0) or not (0 <= yy < h and 0 <= xx < w):
                        continue
                    if mask is not None and not mask[0, 0, yy, xx]:
                        continue
                    d = 0.0
                    if t_e > 0:
                        d = (1 - float((chrom[:, y, x] * chrom[:, yy, xx]).sum())) / t_e
                    if t_d > 0:
                        d = max(d, abs(float(logp[y, x] - logp[yy, xx])) / t_d)
                    e[y, x] = max(float(e[y, x]), d)
    return torch.exp(-(e**2))


@pytest.mark.parametrize("t_e, t_d", [(0.015, 0.0), (0.0, 0.5), (0.03, 0.5)])
@pytest.mark.parametrize("masked", [False, True])
def test_edge_confidence_is_the_largest_deviation_over_the_eight_neighbours(t_e, t_d, masked):
    g = torch.Generator().manual_seed(3)
    img = 0.05 + torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64)
    img[..., 2:4, 2:5] = img[..., 2:3, 2:3]  # a patch of one colour: confidence 1 inside
    mask = torch.rand(1, 1, 6, 7, generator=g) > 0.3 if masked else None
    got = edge_confidence(img, t_e, mask=mask, t_d=t_d)
    want = _edge_reference(img, t_e, t_d, mask)[None, None]
    assert torch.allclose(got, want, atol=1e-12)
    assert float(got.min()) < 0.5  # the random colours do mark edges


def test_a_pair_cut_by_its_colour_asks_for_no_step_at_partial_confidence():
    # green | white; the pair across the edge is cut by its colour. At partial confidence c it
    # is half a smoothness tie: weight (1 - c) per unit dark factor, target 0 (no share of the
    # intensity step). A pair within one colour keeps its full target at any confidence
    img = torch.empty(1, 3, 1, 4)
    img[..., :2] = torch.tensor([0.15, 0.45, 0.15]).view(3, 1, 1)
    img[..., 2:] = 0.8
    img[..., 3] *= 0.9
    st = shading_stencil(1, 4)
    conf = torch.full((1, 1, 1, 4), 0.5)
    full = retinex_term(img, st)
    half = retinex_term(img, st, confidence=conf)
    dark = 1 + math.exp(-(0.25**2 + 0.8**2) / 0.05**2)
    assert float(full.weights[0, 0, 0, 1]) < 1e-12
    assert float(half.weights[0, 0, 0, 1]) == pytest.approx(0.5 * dark, rel=1e-4)
    assert float(half.weighted_target[0, 0, 0, 1]) == pytest.approx(0.0, abs=1e-9)
    # (0, 2)-(0, 3): one colour, both asks agree on the weight; the target is 0.5 * log 0.9 / 1
    assert float(half.weights[0, 0, 0, 2]) == pytest.approx(float(full.weights[0, 0, 0, 2]))
    want = 0.5 * math.log(1 / 0.9) * float(full.weights[0, 0, 0, 2])
    assert float(half.weighted_target[0, 0, 0, 2]) == pytest.approx(want, rel=1e-4)


def test_brightness_steps_are_marked_only_with_t_d():
    # black ink | white paper, one chromaticity: t_e alone sees no edge, t_d marks both sides
    img = torch.full((1, 3, 3, 6), 0.8)
    img[..., :3] = 0.03
    assert torch.all(edge_confidence(img, 0.015) == 1)
    marks = edge_confidence(img, 0.015, t_d=0.5)[0, 0]
    assert torch.all(marks[:, 2:4] < 1e-6) and torch.all(marks[:, [0, 1, 4, 5]] == 1)
    assert torch.equal(edge_confidence(img, 0.0, t_d=0.5), edge_confidence(img, 0.015, t_d=0.5))
    # a gentle ramp of light (10% per pixel, log step 0.095) is barely marked
    ramp = 0.5 * 1.1 ** torch.arange(6.0).view(1, 1, 1, 6).expand(1, 3, 3, 6)
    assert float(edge_confidence(ramp, 0.0, t_d=0.5).min()) > 0.96
    with pytest.raises(ParameterError, match="t_d"):
        edge_confidence(img, 0.0)
    with pytest.raises(ParameterError, match="t_d"):
        retinex_weights(img, shading_stencil(3, 6), t_d=-1.0)


def test_thin_strokes_are_marked_with_t_h_but_steps_are_not():
    # a 2 px dark line on paper, and a sharp step of light (a shadow's edge) elsewhere
    img = torch.full((1, 3, 20, 16), 0.8)
    img[..., 3:5, :] = 0.03  # the line
    img[..., 12:, 8:] *= 0.2  # the step: one colour, 5x darker
    marks = edge_confidence(img, 0.0, t_h=0.5)[0, 0]
    assert torch.all(marks[2:6] < 1e-6)  # the line and the pixels beside it
    assert torch.all(marks[7:] == 1) and torch.all(marks[:1] == 1)  # step and paper
    # t_d marks the step's sides as well as the line's
    assert float(edge_confidence(img, 0.0, t_d=0.5)[0, 0, 15, 7]) < 1e-3
    # a thin masked object (a 3 px wide handle) against its blacked-out outside is not a
    # stroke: the outside takes no part; without the mask it would be one
    obj = torch.zeros(1, 3, 12, 16)
    obj[..., 2:10, 6:9] = 0.6
    mask = obj[:, :1] > 0
    assert torch.all(edge_confidence(obj, 0.0, mask=mask, t_h=0.5)[mask] == 1)
    assert float(edge_confidence(obj, 0.0, t_h=0.5)[0, 0, 5, 7]) < 1e-6
    with pytest.raises(ParameterError, match="t_h"):
        retinex_weights(img, shading_stencil(20, 16), t_h=-1.0)
