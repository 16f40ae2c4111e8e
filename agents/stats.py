"""Statistics for reporting RL across runs: the interquartile mean (IQM) with a
stratified-bootstrap confidence interval (Agarwal et al., NeurIPS 2021, "Deep RL at the
edge of the statistical precipice"; the maths of the ``rliable`` package)."""

from __future__ import annotations

import numpy as np

__all__ = ["SEEDS_FOR_AN_IQM", "iqm", "iqm_interval"]

#: The fewest runs (seeds) whose IQM the reports quote: with 1 or 2 the IQM is the mean of all
#: of them and its interval says little, so reports list each seed instead.
SEEDS_FOR_AN_IQM = 3


def iqm(scores) -> float:
    """Interquartile mean: the mean of ``scores`` (runs) after trimming 25 % at each end
    (``int(0.25 n)`` runs), as rliable computes it (``scipy.stats.trim_mean(x, 0.25)``)."""
    from scipy.stats import trim_mean

    x = np.asarray(scores, dtype=np.float64).ravel()
    if len(x) == 0:
        raise ValueError("iqm of no scores")
    return float(trim_mean(x, 0.25))


def iqm_interval(scores, confidence: float = 0.95, reps: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the IQM over runs (for one task, the stratified
    bootstrap of rliable resamples the runs with replacement)."""
    x = np.asarray(scores, dtype=np.float64).ravel()
    if len(x) == 0:
        raise ValueError("interval of no scores")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    samples = x[rng.integers(0, len(x), (reps, len(x)))]
    stats = np.array([iqm(s) for s in samples])
    alpha = (1 - confidence) / 2
    return float(np.quantile(stats, alpha)), float(np.quantile(stats, 1 - alpha))
