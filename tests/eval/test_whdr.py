import json
import math

import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval import whdr


def _judgements():
    # 4x4 reflectance; point (x, y) reads row int(y*4), col int(x*4)
    points = [
        {"id": 1, "x": 0.1, "y": 0.1, "opaque": True},  # (0, 0)
        {"id": 2, "x": 0.6, "y": 0.1, "opaque": True},  # (0, 2)
        {"id": 3, "x": 0.1, "y": 0.9, "opaque": True},  # (3, 0)
        {"id": 4, "x": 0.9, "y": 0.9, "opaque": False},  # (3, 3)
        {"id": 5, "x": 1.0, "y": 1.0, "opaque": True},  # clamped to (3, 3)
    ]
    comps = [
        {"point1": 1, "point2": 2, "darker": "1", "darker_score": 1.0},  # agrees ('1')
        {"point1": 1, "point2": 3, "darker": "2", "darker_score": 0.5},  # alg 'E' -> error
        {"point1": 2, "point2": 1, "darker": "2", "darker_score": 0.8},  # agrees ('2')
        {"point1": 1, "point2": 5, "darker": "E", "darker_score": 0.3},  # alg '1' -> error
        {"point1": 1, "point2": 4, "darker": "2", "darker_score": 9.0},  # non-opaque: ignored
        {"point1": 1, "point2": 2, "darker": "2", "darker_score": 0.0},  # zero score: ignored
        {"point1": 1, "point2": 2, "darker": None, "darker_score": 2.0},  # null: ignored
        {"point1": 1, "point2": 2, "darker": "2", "darker_score": None},  # null score: ignored
    ]
    return {"intrinsic_points": points, "intrinsic_comparisons": comps}


def _reflectance():
    r = np.full((4, 4, 3), 0.5)
    r[0, 2] = 1.0  # point 2 brighter than point 1 -> '1' is darker
    r[3, 0] = 0.52  # within delta of point 1 -> 'E'
    r[3, 3] = 2.0  # point 5 brighter
    return r


def test_whdr_hand_computed():
    expected = (0.5 + 0.3) / (1.0 + 0.5 + 0.8 + 0.3)
    assert whdr(_reflectance(), _judgements()) == pytest.approx(expected)


def test_whdr_delta_changes_answer():
    # delta = 5: every answer is 'E'; errors on comps 1, 2, 3 (weights 1, .5, .8)
    assert whdr(_reflectance(), _judgements(), delta=5.0) == pytest.approx(2.3 / 2.6)
    # delta = 0: pair (1, 3) is answered '1' (0.52 > 0.5), still != '2'
    assert whdr(_reflectance(), _judgements(), delta=0.0) == pytest.approx(0.8 / 2.6)


def test_whdr_formats_and_path(tmp_path):
    r = _reflectance()
    ref = whdr(r, _judgements())
    t = torch.from_numpy(r).permute(2, 0, 1)
    assert whdr(t, _judgements()) == pytest.approx(ref)
    assert whdr(t[None].float(), _judgements()) == pytest.approx(ref)
    p = tmp_path / "1.json"
    p.write_text(json.dumps(_judgements()))
    assert whdr(r, p) == pytest.approx(ref)
    assert whdr(r * 7.0, str(p)) == pytest.approx(ref)  # scale invariant


def test_whdr_no_valid_comparison_is_nan():
    j = _judgements()
    j["intrinsic_comparisons"] = j["intrinsic_comparisons"][4:]
    assert math.isnan(whdr(_reflectance(), j))


def test_whdr_errors(tmp_path):
    with pytest.raises(ParameterError):
        whdr(_reflectance(), {"intrinsic_points": []})
    with pytest.raises(ParameterError):
        whdr(_reflectance(), tmp_path / "missing.json")
    with pytest.raises(ShapeError):
        whdr(torch.rand(2, 3, 4, 4), _judgements())
    with pytest.raises(ParameterError):
        whdr(_reflectance(), _judgements(), delta=-1)
