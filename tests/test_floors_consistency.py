"""scripts/floors_consistency.py's measures: the model error's autocovariance over the recorded
updates (gaps included) and least squares' expected NEES for correlated noise, against a Monte
Carlo of the same least squares."""

from __future__ import annotations

import numpy as np
import pytest
from test_scripts import load


@pytest.fixture(scope="module")
def floors():
    return load("floors_consistency")


def _log(rng, counts, residuals, pi, cov):
    """Updates (z, Y, b, R) at ``counts`` whose residual at ``pi`` is ``residuals``."""
    log = []
    for r in residuals:
        y, b = rng.standard_normal((6, 10)), rng.standard_normal(6)
        log.append((y @ pi + b + r, y, b, cov))
    return log


def test_model_error_autocovariance_skips_the_gaps(floors):
    """C(L) averages r_k r_(k+L)^T over the pairs of recorded updates exactly L apart."""
    rng = np.random.default_rng(0)
    counts = np.array([0, 1, 2, 4, 5, 8])
    r = rng.standard_normal((counts.size, 6))
    pi = rng.standard_normal(10)
    row = {"log": _log(rng, counts, r, pi, np.eye(6)), "counts": counts, "truth": pi}
    cov = floors.model_error_autocovariance(row, 3)
    at = {c: k for k, c in enumerate(counts)}
    for lag in range(4):
        pairs = [(at[c], at[c + lag]) for c in counts if c + lag in at]
        expected = sum(np.outer(r[i], r[j]) for i, j in pairs) / len(pairs)
        np.testing.assert_allclose(cov[lag], expected, rtol=1e-12, atol=1e-12)


def test_least_squares_expected_nees_matches_monte_carlo(floors):
    """For MA(2) noise independent of a slow regressor (C(L) = sum_i B_i B_(i+L)^T), weighted
    by its per-update covariance C(0) as if white, with a gap in the updates: the mean realised
    NEES over draws equals tr(F^-1 B), and is well above the white 10 (the check can fail)."""
    rng = np.random.default_rng(1)
    counts = np.concatenate((np.arange(20), np.arange(23, 43)))
    taps = [np.eye(6) + 0.2 * rng.standard_normal((6, 6)) for _ in range(3)]
    lag_cov = np.stack([sum(taps[i] @ taps[i + lag].T for i in range(3 - lag)) for lag in range(3)])
    pi = rng.standard_normal(10)
    # A slowly varying regressor sees the noise's correlation (a white one would not).
    regressors = rng.standard_normal((6, 10)) + 0.3 * rng.standard_normal((counts.size, 6, 10))
    offsets = rng.standard_normal((counts.size, 6))
    n_draws = 1500
    realised = np.empty(n_draws)
    expected = None
    for d in range(n_draws):
        white = rng.standard_normal((counts[-1] + 3, 6))
        noise = sum(white[2 - i : white.shape[0] - i] @ taps[i].T for i in range(3))[counts]
        log = [
            (y @ pi + b + n, y, b, lag_cov[0])
            for y, b, n in zip(regressors, offsets, noise, strict=True)
        ]
        realised[d], expected = floors.least_squares_nees(log, counts, pi, lag_cov)
    error = realised.std() / np.sqrt(n_draws)
    assert abs(realised.mean() - expected) < 4 * error
    assert expected > 15
