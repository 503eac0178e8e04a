"""Scoring one decomposition against a sample (``torchiid.eval.scoring``)."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval import DATASETS, METRICS, DenseSample, local_mse, mit_lmse, score_sample


def _sample(h=24, w=28):
    g = torch.Generator().manual_seed(0)
    refl = torch.rand(3, h, w, generator=g) * 0.8 + 0.1
    shading = torch.rand(1, h, w, generator=g) * 0.7 + 0.3
    mask = torch.ones(1, h, w, dtype=torch.bool)
    return DenseSample("a", refl * shading, refl, shading, mask)


def test_score_sample_checks_sizes_and_the_dataset():
    s = _sample()
    with pytest.raises(ShapeError, match="shading"):
        score_sample("dense", s, s.reflectance[None], torch.ones(1, 1, 5, 5))
    with pytest.raises(ParameterError, match="unknown dataset 'kitti'; choose one of iiw"):
        score_sample("kitti", s, s.reflectance[None], s.shading[None])


def test_mit_scores_are_the_lmse_and_its_halves():
    s = _sample()
    est_r, est_s = s.image[None], torch.ones(1, 1, 24, 28)
    row = score_sample("mit", s, est_r, est_s)
    assert list(row) == list(METRICS["mit"]) and set(METRICS) == set(DATASETS)
    true_r, true_s, m = s.reflectance[None], s.shading[None], s.mask[None]
    assert row["lmse"] == pytest.approx(float(mit_lmse(true_r, true_s, est_r, est_s, m)[0]))
    gray = est_r.mean(1, keepdim=True)
    assert row["lmse_reflectance"] == pytest.approx(
        float(local_mse(true_r.mean(1, keepdim=True), gray, m)[0])
    )
    assert row["lmse"] == pytest.approx((row["lmse_shading"] + row["lmse_reflectance"]) / 2)
