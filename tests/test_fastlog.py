"""The inlinable logarithm used by the vectorised Neo-Hookean kernel agrees with math.log."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from heml_gym.fastlog import SMALLEST_NORMAL, log_positive


@nb.njit
def _apply(xs, out):
    for i in range(xs.shape[0]):
        out[i] = log_positive(xs[i])


def test_log_positive_within_two_ulp_of_math_log():
    rng = np.random.default_rng(0)
    xs = np.concatenate([
        rng.uniform(0.05, 20.0, 200_000),  # the volume ratios a simulation sees
        1.0 + rng.uniform(-1e-8, 1e-8, 10_000),  # near rest, where ln J ~ J - 1
        np.exp(rng.uniform(-700, 700, 10_000)),  # every exponent
        [SMALLEST_NORMAL, 1.0, 2.0, 0.5, math.sqrt(2.0), np.nextafter(math.sqrt(2.0), 2.0)],
    ])
    out = np.empty_like(xs)
    _apply(xs, out)
    ref = np.log(xs)
    nonzero = ref != 0
    ulps = np.abs(out - ref)[nonzero] / np.spacing(np.abs(ref[nonzero]))
    assert ulps.max() <= 2.0
    assert out[np.flatnonzero(xs == 1.0)[0]] == 0.0
