"""Percentile-bootstrap intervals of ratios of sums over clusters (scenes, vehicles, seeds).

A share such as identified targets / targets, lane changes caught / lane changes or wrong
highlight episodes / drawn episodes is a ratio of two sums over units that are not independent:
one occluded cluster of cars fails together, one vehicle's ticks follow each other, one seed's
episodes share its traffic. So the clusters (a scene, a vehicle, a seed) are resampled with
replacement, not the units, and each resample's statistic is its ratio of sums (a cluster weighs
what it holds, not one vote each). Every series of one study is evaluated on the same resamples,
so the difference of two series is paired.

    weights = cluster_weights(n_clusters, resamples, seed)
    draws = ratio_draws(weights, numerator_per_cluster, denominator_per_cluster)
    low, high = percentile_interval(draws)
"""

from __future__ import annotations

import numpy as np


def cluster_weights(n_clusters: int, resamples: int, seed: int = 0) -> np.ndarray:
    """(resamples, n_clusters): how often each cluster is drawn in each resample of n_clusters draws
    with replacement. Seeded: the same arguments give the same weights."""
    if n_clusters < 1 or resamples < 1:
        raise ValueError(f"cluster bootstrap: need at least one cluster and one resample, "
                         f"got {n_clusters} clusters, {resamples} resamples")
    rng = np.random.default_rng(seed)
    return rng.multinomial(n_clusters, np.full(n_clusters, 1.0 / n_clusters), size=resamples).astype(float)


def ratio_draws(weights: np.ndarray, numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """Per resample, sum(numerator) / sum(denominator) over the drawn clusters: nan where a resample
    drew no denominator (e.g. no target). ``numerator``, ``denominator``: one value per cluster."""
    num, den = np.asarray(numerator, dtype=float), np.asarray(denominator, dtype=float)
    if num.shape != (weights.shape[1],) or den.shape != num.shape:
        raise ValueError(f"cluster bootstrap: {weights.shape[1]} clusters, but numerator {num.shape} "
                         f"and denominator {den.shape} values")
    with np.errstate(invalid="ignore", divide="ignore"):
        return (weights @ num) / (weights @ den)


def percentile_interval(draws: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` percentile interval of the finite draws; (nan, nan) if there is none."""
    finite = np.asarray(draws, dtype=float)
    finite = finite[np.isfinite(finite)]
    if not len(finite):
        return float("nan"), float("nan")
    low, high = np.percentile(finite, (100 * (1 - level) / 2, 100 * (1 + level) / 2))
    return float(low), float(high)
