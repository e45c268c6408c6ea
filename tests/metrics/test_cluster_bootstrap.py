"""The cluster bootstrap of ratios of sums: hand-computed resamples, SciPy's own percentile
bootstrap of the same statistic as an independent reference, and the interval's edge cases."""

import numpy as np
import pytest
from scipy import stats

from vcfusion.metrics.cluster_bootstrap import cluster_weights, percentile_interval, ratio_draws


def test_a_resample_is_the_ratio_of_the_drawn_clusters_sums():
    # three clusters of 2, 4 and 10 units; resample 1 draws the first twice and the third once,
    # resample 2 the second three times, resample 3 only the first (whose denominator is 0)
    weights = np.array([[2.0, 0.0, 1.0], [0.0, 3.0, 0.0], [3.0, 0.0, 0.0]])
    draws = ratio_draws(weights, np.array([0.0, 2.0, 3.0]), np.array([0.0, 4.0, 10.0]))
    assert draws[0] == pytest.approx(3.0 / 10.0)
    assert draws[1] == pytest.approx(6.0 / 12.0)
    assert np.isnan(draws[2])
    # the point (every cluster once) is the ratio of sums, 5 / 15, not the mean of the clusters' ratios (0.27)
    assert ratio_draws(np.ones((1, 3)), [0.0, 2.0, 3.0], [1.0, 4.0, 10.0])[0] == pytest.approx(5.0 / 15.0)


def test_the_weights_draw_n_clusters_with_replacement_and_are_seeded():
    w = cluster_weights(7, 500, seed=3)
    assert w.shape == (500, 7)
    assert np.all(w.sum(axis=1) == 7) and np.all(w >= 0)
    assert np.array_equal(w, cluster_weights(7, 500, seed=3))
    assert not np.array_equal(w, cluster_weights(7, 500, seed=4))
    # each cluster is drawn once per resample on average
    assert w.mean() == pytest.approx(1.0, abs=0.05)


def test_the_interval_agrees_with_scipys_percentile_bootstrap():
    """Clusters of unequal size and rate; the statistic resampled by SciPy over the same clusters
    (paired numerator and denominator). Both are Monte Carlo: they agree within a point."""
    rng = np.random.default_rng(11)
    size = rng.integers(1, 30, 80).astype(float)
    num = rng.binomial(size.astype(int), rng.uniform(0.02, 0.3, 80)).astype(float)
    ours = percentile_interval(ratio_draws(cluster_weights(80, 20000, seed=0), num, size))
    ref = stats.bootstrap((num, size), lambda n, d, axis=-1: n.sum(axis=axis) / d.sum(axis=axis), paired=True,
                          vectorized=True, n_resamples=20000, method="percentile", random_state=1)
    assert ours == pytest.approx((ref.confidence_interval.low, ref.confidence_interval.high), abs=0.01)
    assert ours[0] < num.sum() / size.sum() < ours[1]


def test_the_difference_of_two_series_on_the_same_resamples_is_paired():
    """Series b is series a plus one unit in cluster 0: their difference is zero exactly in the
    resamples without cluster 0, so its interval's lower end is 0 (not below, as unpaired)."""
    den = np.full(20, 10.0)
    a = np.tile([1.0, 2.0], 10)
    b = a.copy()
    b[0] += 1
    w = cluster_weights(20, 4000, seed=0)
    diff = ratio_draws(w, b, den) - ratio_draws(w, a, den)
    assert np.all(diff[w[:, 0] == 0] == 0) and np.all(diff[w[:, 0] > 0] > 0)
    assert percentile_interval(diff)[0] == 0.0


def test_the_interval_keeps_finite_draws_and_its_level():
    draws = np.concatenate([np.arange(101.0), [np.nan, np.inf]])
    assert percentile_interval(draws, level=0.9) == pytest.approx((5.0, 95.0))
    assert percentile_interval(draws) == pytest.approx((2.5, 97.5))
    low, high = percentile_interval(np.array([np.nan, np.nan]))
    assert np.isnan(low) and np.isnan(high)


def test_mismatched_clusters_are_refused():
    with pytest.raises(ValueError, match="3 clusters, but numerator"):
        ratio_draws(np.ones((2, 3)), np.ones(4), np.ones(4))
    with pytest.raises(ValueError, match="at least one cluster"):
        cluster_weights(0, 10)
