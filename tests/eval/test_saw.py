import math

import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval import average_precision, saw_ap, saw_scores
from torchiid.eval.saw import SAW_NORMAL, SAW_SHADOW, SAW_SMOOTH, SAW_UNLABELED


def test_average_precision_by_hand():
    t = torch.tensor([1, 0, 1, 0])
    assert average_precision(torch.tensor([4.0, 3.0, 2.0, 1.0]), t).item() == pytest.approx(5 / 6)
    assert average_precision(torch.tensor([4.0, 1.0, 3.0, 2.0]), t).item() == pytest.approx(1.0)
    # worst ranking: positives last -> precision 1/3 at recall .5, 2/4 at recall 1
    worst = average_precision(torch.tensor([1.0, 4.0, 2.0, 3.0]), t).item()
    assert worst == pytest.approx(0.5 * (1 / 3) + 0.5 * (2 / 4))
    # ties enter together: one threshold, precision 1/2
    assert average_precision(torch.ones(2), torch.tensor([1, 0])).item() == pytest.approx(0.5)
    assert math.isnan(average_precision(torch.rand(3), torch.zeros(3)).item())


def _step_scene(h=40, w=40, edge=20):
    shading = torch.full((h, w), 0.5)
    shading[:, edge:] = 0.1  # shadow: a step of log(5)
    labels = torch.full((h, w), SAW_UNLABELED)
    labels[5:35, 2:12] = SAW_SMOOTH
    labels[5:35, 28:38] = SAW_SMOOTH
    return shading, labels


def test_saw_ap_perfect_and_boundary_tolerance():
    shading, labels = _step_scene()
    labels[5:35, 19:21] = SAW_SHADOW
    assert saw_ap(shading, labels) == pytest.approx(1.0)
    assert saw_ap(shading * 3.0, labels) == pytest.approx(1.0)  # log gradient: scale free
    # boundary annotated 3 px off the true edge: the max filter (r=5) still finds it,
    # without it those pixels look smooth and tie with the positives
    off = labels.clone()
    off[5:35, 19:21] = SAW_UNLABELED
    off[5:35, 15:17] = SAW_NORMAL
    assert saw_ap(shading, off, boundary_radius=5) == pytest.approx(1.0)
    n_pos, n_neg = int((off == SAW_SMOOTH).sum()), int((off == SAW_NORMAL).sum())
    tied = n_pos / (n_pos + n_neg)  # all scores 0: one threshold
    assert saw_ap(shading, off, boundary_radius=0) == pytest.approx(tied)


def test_saw_ap_crafted_ranking():
    # smooth pixels on both flat sides (score 0) plus a ramp region with a known slope
    shading, labels = _step_scene()
    labels[5:35, 19:21] = SAW_SHADOW
    ramp = shading.clone()
    ramp[:, 28:] = 0.1 * torch.exp(0.05 * torch.arange(12.0))  # log slope 0.05 < the step
    # ranking: 300 smooth (flat, score 0), then 300 smooth on the ramp, then 60 shadow
    assert saw_ap(ramp, labels, boundary_radius=0) == pytest.approx(1.0)
    # mark the ramp as shadow instead: 300 positives first, then 300 + 60 negatives
    lab2 = labels.clone()
    lab2[5:35, 28:38] = SAW_SHADOW
    assert saw_ap(ramp, lab2, boundary_radius=0) == pytest.approx(1.0)
    # now the flat left side is shadow: 300 negatives rank above every positive
    lab3 = labels.clone()
    lab3[5:35, 2:12] = SAW_SHADOW
    assert saw_ap(ramp, lab3, boundary_radius=0) < 0.5
    # pooled over images equals the AP of the concatenated scores
    pooled = saw_ap([shading, ramp], [labels, lab3], boundary_radius=0)
    a, ta = saw_scores(shading, labels, boundary_radius=0)
    b, tb = saw_scores(ramp, lab3, boundary_radius=0)
    assert pooled == pytest.approx(average_precision(torch.cat([a, b]), torch.cat([ta, tb])).item())


def test_saw_ap_inverted_labels_by_hand():
    shading, labels = _step_scene()
    inv = torch.full_like(labels, SAW_UNLABELED)
    inv[5:35, 19:21] = SAW_SMOOTH  # 60 positives on the edge
    inv[5:35, 2:12] = SAW_SHADOW  # 300 negatives on a flat area, ranked first
    assert saw_ap(shading, inv, boundary_radius=0) == pytest.approx(60 / 360)


def test_saw_color_shading_and_errors():
    shading, labels = _step_scene()
    labels[5:35, 19:21] = SAW_SHADOW
    rgb = shading[None].expand(3, 40, 40)[None]
    assert saw_ap(rgb, labels) == pytest.approx(saw_ap(shading, labels))
    with pytest.raises(ShapeError):
        saw_ap(shading, labels[:-1])
    with pytest.raises(ParameterError):
        saw_ap(shading, labels, boundary_radius=-1)
    with pytest.raises(ShapeError):
        saw_ap([shading], [labels, labels])
