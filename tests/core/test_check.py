"""Input checks: the finite check's fast path gives the same answers as the full one."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.check import check_finite
from torchiid.core.exceptions import ImageError


def test_finite_values_whose_sum_overflows_pass():
    x = torch.full((1, 3, 8, 8), 3e38)  # each finite, the float32 sum is inf
    assert not torch.isfinite(x.sum())
    check_finite(x, "x")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_one_bad_value_is_found_and_counted(bad):
    x = torch.rand(1, 3, 16, 16)
    x[0, 1, 5, 7] = bad
    with pytest.raises(ImageError, match="x contains (1 NaN and 0|0 NaN and 1) infinite"):
        check_finite(x, "x")


def test_opposite_infinities_are_not_mistaken_for_finite():
    x = torch.zeros(4)
    x[0], x[1] = float("inf"), -float("inf")  # their sum is NaN, still caught
    with pytest.raises(ImageError, match="0 NaN and 2 infinite"):
        check_finite(x)


def test_empty_and_integer_tensors_pass():
    check_finite(torch.empty(0))
    check_finite(torch.arange(10))
