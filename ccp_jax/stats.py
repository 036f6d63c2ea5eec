"""Few-seed statistics for RL results: IQM, stratified-bootstrap intervals, probability of improvement.

The estimators of Agarwal et al., "Deep RL at the edge of the statistical
precipice" (NeurIPS 2021, the `rliable` library), in plain numpy:

* `iqm`: the interquartile mean, the mean of the middle 50 % of the scores
  (rliable's `scipy.stats.trim_mean(x, 0.25)`), robust to one outlying seed.
* `bootstrap_ci`: a percentile interval of any aggregate, resampling the runs of
  each task independently (stratified by task), so a task with few seeds is never
  dropped from a resample.
* `probability_of_improvement`: P(X > Y) + P(X = Y) / 2 for a run of method X and
  a run of method Y on the same task, averaged over tasks.

Scores are arrays shaped [runs, tasks] (one column per task; a single task is a
[runs] vector). Every function is deterministic given its `seed`.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

Aggregate = Callable[[np.ndarray], float]


def _columns(scores: np.ndarray | Sequence) -> np.ndarray:
    """[runs, tasks] float array from a [runs] or [runs, tasks] input; refuses an empty one."""
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"scores: expected a non-empty [runs] or [runs, tasks] array, got shape {x.shape}")
    return x


def mean(scores: np.ndarray | Sequence) -> float:
    """The mean over every run of every task."""
    return float(np.mean(_columns(scores)))


def iqm(scores: np.ndarray | Sequence) -> float:
    """Interquartile mean over every run of every task: int(n / 4) scores cut from each end of the sorted n."""
    x = np.sort(_columns(scores).ravel())
    cut = int(0.25 * x.size)
    return float(np.mean(x[cut:x.size - cut]))


def bootstrap_ci(scores: np.ndarray | Sequence, aggregate: Aggregate = iqm, reps: int = 2000,
                 confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile interval of `aggregate` over `reps` stratified resamples of `scores` [runs, tasks].

    Each resample draws, for each task, as many runs as it has, with replacement, from that task's runs.
    One run per task has no spread to resample: the interval is then the point value.
    """
    x = _columns(scores)
    runs, tasks = x.shape
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, runs, size=(reps, runs, tasks))  # [reps, runs, tasks] row indices per task
    resampled = np.take_along_axis(x[None], picks, axis=1)
    values = np.array([aggregate(r) for r in resampled])
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def probability_of_improvement(x: np.ndarray | Sequence, y: np.ndarray | Sequence) -> float:
    """P(X > Y) + P(X = Y) / 2 for runs X of one method and Y of another, per task [runs, tasks], mean over tasks."""
    a, b = _columns(x), _columns(y)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"x and y: different task counts ({a.shape[1]} and {b.shape[1]})")
    per_task = [np.mean((a[:, None, t] > b[None, :, t]) + 0.5 * (a[:, None, t] == b[None, :, t]))
                for t in range(a.shape[1])]
    return float(np.mean(per_task))


def probability_of_improvement_ci(x: np.ndarray | Sequence, y: np.ndarray | Sequence, reps: int = 2000,
                                  confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile interval of `probability_of_improvement`, resampling each method's runs per task."""
    a, b = _columns(x), _columns(y)
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(reps):
        ra = np.take_along_axis(a, rng.integers(0, a.shape[0], size=a.shape), axis=0)
        rb = np.take_along_axis(b, rng.integers(0, b.shape[0], size=b.shape), axis=0)
        values.append(probability_of_improvement(ra, rb))
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def curve_band(curves: np.ndarray, reps: int = 1000, confidence: float = 0.95,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over runs and its bootstrap interval at every point of `curves` [runs, points]: three [points] arrays."""
    c = np.asarray(curves, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] == 0:
        raise ValueError(f"curves: expected a non-empty [runs, points] array, got shape {c.shape}")
    rng = np.random.default_rng(seed)
    means = c[rng.integers(0, c.shape[0], size=(reps, c.shape[0]))].mean(axis=1)  # [reps, points]
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(means, [tail, 100 - tail], axis=0)
    return c.mean(axis=0), low, high
