"""The statistics of benchmark/mnist_seeds.py and benchmark/goal_dqn_seeds.py against values worked out by hand."""

import sys
from math import comb
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmark"))

import goal_dqn_seeds
import mnist_seeds


def test_permutation_p_of_fully_separated_groups_is_one_split_in_all():
    treated, control = np.array([3.0, 4.0, 5.0]), np.array([0.0, 1.0, 2.0])
    assert mnist_seeds.permutation_p(treated, control) == pytest.approx(1 / comb(6, 3))
    assert goal_dqn_seeds.permutation_p(treated, control, higher_is_better=True) == pytest.approx(1 / 20)
    # lower is better: the same data is the least favourable split of all
    assert goal_dqn_seeds.permutation_p(treated, control, higher_is_better=False) == pytest.approx(1.0)
    assert goal_dqn_seeds.permutation_p(control, treated, higher_is_better=False) == pytest.approx(1 / 20)


def test_permutation_p_counts_ties_as_extreme():
    same = np.array([1.0, 1.0])
    assert mnist_seeds.permutation_p(same, same) == 1.0  # every split gives the observed difference, 0


def test_spearman_uses_ranks_with_shared_ranks_for_ties():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    assert mnist_seeds.spearman(a, a**3) == pytest.approx(1.0)  # monotone, not linear
    assert mnist_seeds.spearman(a, -a) == pytest.approx(-1.0)
    np.testing.assert_allclose(mnist_seeds.ranks(np.array([5.0, 1.0, 5.0, 2.0])), [2.5, 0.0, 2.5, 1.0])


def test_bootstrap_interval_brackets_the_difference_and_is_a_point_for_constant_groups():
    rng = np.random.default_rng(0)
    assert goal_dqn_seeds.bootstrap_interval(np.full(5, 2.0), np.full(5, 0.5), rng) == (1.5, 1.5)
    low, high = goal_dqn_seeds.bootstrap_interval(np.array([1.0, 2, 3, 4, 5]), np.array([0.0, 1, 2, 3, 4]), rng)
    assert low < 1.0 < high and high - low < 4.0


def test_late_mean_averages_the_last_tenth_of_steps():
    steps = np.arange(0, 101, dtype=float)
    values = np.where(steps >= 90, 7.0, 0.0)
    assert mnist_seeds.late_mean((steps, values)) == 7.0
