"""``recipes/analysis/guidance.py``: distances to the nearest example, the rank correlation and the groups by
distance, against values worked out by hand (its reading of a saved run: tests/test_saved_runs.py)."""
from __future__ import annotations

import math

import pytest
import torch

from torchrl_reset_recipes.analysis.guidance import guidance_rows, nearest_distances, spearman


def test_each_row_takes_its_nearest_example_after_the_scaling():
    rows = torch.tensor([[0.0, 0.0], [3.0, 4.0], [1.0, 1.0]])
    examples = torch.tensor([[0.0, 0.0], [3.0, 0.0]])
    # unscaled: (0,0) is an example; (3,4) is 4 from (3,0) and 5 from (0,0); (1,1) is sqrt(2) from (0,0), sqrt(5) from (3,0)
    assert nearest_distances(rows, examples).tolist() == pytest.approx([0.0, 4.0, math.sqrt(2)])
    # the second entry halved: (3,4) -> (3,2), 2 from (3,0); (1,1) -> (1,0.5), sqrt(1.25) from (0,0)
    scaled = nearest_distances(rows, examples, torch.tensor([1.0, 2.0]))
    assert scaled.tolist() == pytest.approx([0.0, 2.0, math.sqrt(1.25)])
    # chunks change nothing
    assert nearest_distances(rows, examples, chunk=1).tolist() == pytest.approx([0.0, 4.0, math.sqrt(2)])
    with pytest.raises(ValueError, match="one D"):
        nearest_distances(rows, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="no example"):
        nearest_distances(rows, torch.zeros(0, 2))


def test_spearman_ranks_with_ties_and_is_undefined_for_a_constant_side():
    assert spearman(torch.tensor([1.0, 2, 3, 4]), torch.tensor([10.0, 9, 7, 1])) == pytest.approx(-1.0)
    # ranks (1, 2.5, 2.5, 4) against (1, 2, 3, 4): covariance 4.5, variances 4.5 and 5, so sqrt(0.9)
    assert spearman(torch.tensor([1.0, 2, 2, 3]), torch.tensor([1.0, 2, 3, 4])) == pytest.approx(math.sqrt(0.9))
    assert math.isnan(spearman(torch.tensor([1.0, 2, 3]), torch.tensor([0.5, 0.5, 0.5])))


def test_groups_of_equal_size_by_distance_with_their_medians_and_shares():
    distance = torch.tensor([5.0, 1, 3, 2, 4, 6])
    p = torch.tensor([0.1, 0.9, 0.5, 0.7, 0.3, 0.05])
    groups = guidance_rows(distance, p, bins=3, threshold=0.4)
    # sorted by distance: (1, .9) (2, .7) | (3, .5) (4, .3) | (5, .1) (6, .05)
    assert [(g["from"], g["to"], g["rows"]) for g in groups] == [(1, 2, 2), (3, 4, 2), (5, 6, 2)]
    assert [g["median_distance"] for g in groups] == pytest.approx([1.5, 3.5, 5.5])
    assert [g["median_p"] for g in groups] == pytest.approx([0.8, 0.4, 0.075])
    assert [g["at_or_above"] for g in groups] == pytest.approx([1.0, 0.5, 0.0])
    # seven rows in three groups: 3, 2, 2; more groups than rows: one row each
    assert [g["rows"] for g in guidance_rows(torch.arange(7.0), torch.zeros(7), 3, 0.1)] == [3, 2, 2]
    assert [g["rows"] for g in guidance_rows(torch.arange(2.0), torch.zeros(2), 5, 0.1)] == [1, 1]
    with pytest.raises(ValueError, match="at least 1"):
        guidance_rows(distance, p, bins=0, threshold=0.4)
    with pytest.raises(ValueError, match="one distance per p"):
        guidance_rows(distance, p[:3], bins=2, threshold=0.4)
