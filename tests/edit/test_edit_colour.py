"""torchiid.edit.colour: named tints, colour parsing and CIELab."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit import COLOURS, lab_to_linear, linear_to_lab, parse_colour


def test_parse_colour_reads_names_hex_and_triples():
    assert parse_colour("#ff8000") == (1.0, 128 / 255, 0.0)
    assert parse_colour("0.5,0.5,1") == (0.5, 0.5, 1.0)
    assert parse_colour("255,0,51") == (1.0, 0.0, 0.2)
    assert parse_colour("Warm") == COLOURS["warm"]
    assert parse_colour([0.1, 0.2, 0.3]) == (0.1, 0.2, 0.3)


@pytest.mark.parametrize("bad", ["purple-ish", "#12345g", "1,2", "-1,0,0", "300,0,0", "nan,0,0"])
def test_unreadable_colours_are_refused(bad):
    with pytest.raises(ParameterError):
        parse_colour(bad)


def test_lab_of_known_colours_and_round_trip():
    white = torch.ones(1, 3, 1, 1, dtype=torch.float64)
    want = torch.tensor([100.0, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(linear_to_lab(white).view(3), want, atol=0.01, rtol=0)
    # linear 0.18 gray is L* 49.5 (the sRGB curve, not a plain power law)
    assert abs(float(linear_to_lab(0.18 * white)[0, 0]) - 49.5) < 0.1
    x = torch.rand(2, 3, 5, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = x * 1.5  # values above 1 go through unclipped
    torch.testing.assert_close(lab_to_linear(linear_to_lab(x)), x, atol=1e-6, rtol=1e-6)
