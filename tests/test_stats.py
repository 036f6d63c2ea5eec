"""ccp_jax.stats against hand values: IQM, stratified bootstrap, probability of improvement, curve bands."""
import numpy as np
import pytest

from ccp_jax import stats


def test_iqm_cuts_a_quarter_from_each_end():
    # 8 scores: 2 cut from each end, the mean of 3, 4, 5, 6.
    assert stats.iqm([100, 1, 2, 3, 4, 5, 6, -50]) == pytest.approx(3.5)
    # 5 scores (scipy's trim_mean(x, 0.25)): int(1.25) = 1 cut from each end.
    assert stats.iqm([0.0, 1.0, 1.0, 0.0, 0.5]) == pytest.approx(0.5)
    # Fewer than 4 scores: nothing cut, the plain mean.
    assert stats.iqm([0.0, 1.0, 0.2]) == pytest.approx(0.4)
    # [runs, tasks]: pooled over every run of every task.
    assert stats.iqm(np.array([[1.0, 10.0], [2.0, 20.0]])) == pytest.approx(6.0)


def test_bootstrap_interval_brackets_the_point_and_is_deterministic():
    scores = [0.0, 0.0, 1.0, 1.0, 1.0]
    low, high = stats.bootstrap_ci(scores, stats.mean, reps=4000, seed=3)
    assert 0.0 <= low < 0.6 < high <= 1.0
    assert stats.bootstrap_ci(scores, stats.mean, reps=4000, seed=3) == (low, high)
    # The interval of the mean of a Bernoulli(0.6) sample of 5: the resampled mean takes values k/5.
    assert low in {0.0, 0.2} and high == 1.0


def test_bootstrap_of_identical_runs_is_a_point():
    assert stats.bootstrap_ci([0.7, 0.7, 0.7]) == pytest.approx((0.7, 0.7))


def test_bootstrap_is_stratified_by_task():
    # Task 0 always 0, task 1 always 1: every stratified resample keeps both columns, so the mean is exactly 0.5.
    scores = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    assert stats.bootstrap_ci(scores, stats.mean, reps=500) == pytest.approx((0.5, 0.5))


def test_probability_of_improvement_hand_values():
    assert stats.probability_of_improvement([1.0, 1.0], [0.0, 0.0]) == 1.0
    assert stats.probability_of_improvement([0.0], [1.0]) == 0.0
    # Ties count one half: x = (1, 0), y = (0, 0): pairs 1>0, 1>0, 0=0, 0=0 -> (1 + 1 + 0.5 + 0.5) / 4.
    assert stats.probability_of_improvement([1.0, 0.0], [0.0, 0.0]) == pytest.approx(0.75)
    low, high = stats.probability_of_improvement_ci([1.0, 0.0, 1.0], [0.0, 0.0, 0.5], reps=500)
    assert 0.0 <= low <= stats.probability_of_improvement([1.0, 0.0, 1.0], [0.0, 0.0, 0.5]) <= high <= 1.0


def test_curve_band_mean_and_interval():
    curves = np.array([[0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    mean, low, high = stats.curve_band(curves, reps=500)
    np.testing.assert_allclose(mean, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(low[[0, 2]], [0.0, 1.0])
    np.testing.assert_allclose(high[[0, 2]], [0.0, 1.0])
    assert low[1] == 0.0 and high[1] == 1.0


def test_bad_shapes_name_the_argument():
    with pytest.raises(ValueError, match="scores"):
        stats.iqm([])
    with pytest.raises(ValueError, match="x and y"):
        stats.probability_of_improvement(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="curves"):
        stats.curve_band(np.zeros(3))
