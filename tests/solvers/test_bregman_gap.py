import torch

from torchiid.solvers.bregman_gap import balance, next_check


def test_next_measurement_of_the_gap_comes_where_its_rate_predicts():
    on = torch.tensor([True, True])
    # no earlier measurement: the full interval
    assert next_check(torch.tensor([0.1, 0.2]), None, 5, on, 1e-3, 5) == 5
    # halving per iteration from 0.08 (iteration 5) to 0.02 (iteration 7): 0.02 -> 0.005 in
    # 2 more; the first image to get there decides
    before, now = torch.tensor([0.08, 0.8]), torch.tensor([0.02, 0.2])
    assert next_check(now, (5, before), 7, on, 0.005, 5) == 2
    # at least one iteration, at most check_every
    assert next_check(torch.tensor([0.0051, 1.0]), (6, torch.tensor([0.01, 1.0])), 7, on,
                       0.005, 5) == 1  # fmt: skip
    assert next_check(torch.tensor([0.9, 0.9]), (5, torch.tensor([0.91, 0.91])), 10, on,
                       0.005, 5) == 5  # fmt: skip
    # a gap that grew, or images that stopped, give no rate
    assert next_check(now, (5, now * 0.5), 7, on, 0.005, 5) == 5
    assert next_check(now, (5, before), 7, torch.tensor([False, False]), 0.005, 5) == 5
    # an image already below the tolerance, or frozen, does not set the schedule: the other
    # one, quartering per iteration from 0.2, needs 3 more iterations to get below 0.005
    now, before = torch.tensor([0.004, 0.2]), torch.tensor([0.008, 3.2])
    assert next_check(now, (5, before), 7, on, 0.005, 5) == 3
    fast = torch.tensor([0.0051, 0.2])  # 1 more iteration, but it has stopped
    slow = (5, torch.tensor([0.0102, 3.2]))
    assert next_check(fast, slow, 7, torch.tensor([False, True]), 0.005, 5) == 3
    assert next_check(fast, slow, 7, on, 0.005, 5) == 1


def test_balancing_halves_or_doubles_the_penalty_within_its_range():
    rng, ratios = (1.0, 8.0), (10.0, 1.0)
    assert balance(None, 4.0, rng, ratios) == 4.0  # nothing measured
    assert balance((0.01, 0.2), 4.0, rng, ratios) == 2.0  # dual 20x the primal: lower
    assert balance((0.01, 0.2), 1.5, rng, ratios) == 1.0  # not below the range
    assert balance((0.02, 0.01), 4.0, rng, ratios) == 8.0  # primal dominates: raise
    assert balance((0.02, 0.01), 6.0, rng, ratios) == 8.0
    assert balance((0.01, 0.05), 4.0, rng, ratios) == 4.0  # in between: keep
