"""The errors-in-variables compensation (``estimator.bias_compensation``): its score bias against
a Monte Carlo, and the compensated filter's estimate unbiased where the plain one is not."""

import numpy as np
import pytest

from astrocargo.estimator.bias_compensation import DeferredCompensation, score_bias
from astrocargo.estimator.ukf import InertialParamUKF

CHANNELS, MODES = 2, 3
TRUTH = np.array([1.0, 0.05, -0.02, 0.03, 0.1, 0.12, 0.08, 0.01, 0.0, -0.01])


def _modes(rng):
    """A lag-0 mode covariance Gm (not I) and its groups (``score_bias``)."""
    root = rng.standard_normal((MODES, MODES))
    gm = root @ root.T / MODES + 0.5 * np.eye(MODES)
    return gm, [(slice(0, CHANNELS * MODES), CHANNELS, MODES, gm)]


def _update(rng, gm, noise, at):
    """One update's noisy (z, Y, b), its modes' maps (E at ``at``, dY) and R at ``at``."""
    y0 = rng.standard_normal((6, 10))
    d_y = noise * rng.standard_normal((CHANNELS * MODES, 6, 10))
    d_l = noise * rng.standard_normal((6, CHANNELS * MODES))
    u = (np.linalg.cholesky(gm) @ rng.standard_normal((MODES, CHANNELS))).T.reshape(-1)
    b = rng.standard_normal(6)
    z = y0 @ TRUTH + b + 0.01 * rng.standard_normal(6)
    y_m, b_m = y0 + np.einsum("k,kxp->xp", u, d_y), b + d_l @ u
    balance = d_l + np.einsum("kxp,p->xk", d_y, at)
    cov = balance @ np.kron(np.eye(CHANNELS), gm) @ balance.T + 1e-4 * np.eye(6)
    return (z, y_m, b_m), (balance, d_y), cov


def test_score_bias_matches_monte_carlo():
    """s(x) = E[Y^T R^-1 (z - Y x - b)] - F (pi - x) over the modes' draws, at an x off the
    truth, and its slope -D (s is affine in x)."""
    rng = np.random.default_rng(3)
    gm, groups = _modes(rng)
    y0 = rng.standard_normal((6, 10))
    d_y = 0.3 * rng.standard_normal((CHANNELS * MODES, 6, 10))
    d_l = 0.3 * rng.standard_normal((6, CHANNELS * MODES))
    x = TRUTH + 0.2 * rng.standard_normal(10)
    cov = np.eye(6) + 0.3 * np.ones((6, 6))
    r_inv = np.linalg.inv(cov)
    draws = 200_000
    u = rng.standard_normal((draws, CHANNELS, MODES)) @ np.linalg.cholesky(gm).T
    u = u.reshape(draws, -1)
    y_m = y0 + np.einsum("nk,kxp->nxp", u, d_y)
    residual = np.einsum("xp,p->x", y0, TRUTH - x) - np.einsum("nxp,p->nx", y_m - y0, x)
    residual -= u @ d_l.T
    scores = np.einsum("nxp,xy,ny->np", y_m, r_inv, residual)
    expected = scores.mean(0) - y0.T @ r_inv @ y0 @ (TRUTH - x)
    balance = d_l + np.einsum("kxp,p->xk", d_y, x)
    s, slope = score_bias(balance, d_y, groups, cov)
    stderr = scores.std(0) / np.sqrt(draws)
    assert np.all(np.abs(s - expected) < 4 * stderr + 1e-12)
    assert np.abs(s).max() > 20 * stderr.max()  # the bias is there to be seen
    step = 0.1 * rng.standard_normal(10)
    balance_step = d_l + np.einsum("kxp,p->xk", d_y, x + step)
    np.testing.assert_allclose(score_bias(balance_step, d_y, groups, cov)[0], s - slope @ step)
    assert np.all(np.linalg.eigvalsh(slope) >= -1e-12)


def test_compensated_filter_is_unbiased_where_the_plain_one_is_not():
    """Errors in variables in a Kalman filter on the ten parameters: over 600 runs of 40
    updates, the plain estimate's mass is biased (its mean more than 4 standard errors low),
    the deferred compensation's mean is within 3 standard errors of the truth in every
    parameter and its mass bias under a quarter of the plain one's."""
    rng = np.random.default_rng(0)
    gm, groups = _modes(rng)
    prior = np.array([2.0, 0, 0, 0, 0.3, 0.3, 0.3, 0, 0, 0])
    plain, compensated = [], []
    for _ in range(600):
        ukf = InertialParamUKF(prior, 100.0 * np.eye(10), np.zeros((10, 10)))
        compensation = DeferredCompensation()
        for _ in range(40):
            at = ukf.x.copy()
            measurement, modes, cov = _update(rng, gm, 0.1, at)
            before = ukf.P.copy()
            ukf.predict()
            assert ukf.update_linear(*measurement, cov).accepted
            compensation.add((*score_bias(*modes, groups, cov), at), before, ukf.Q)
        plain.append(ukf.x - TRUTH)
        compensated.append(ukf.x + compensation.offset(ukf.x, ukf.P) - TRUTH)
    plain, compensated = np.array(plain), np.array(compensated)
    t_plain = plain.mean(0) / (plain.std(0) / np.sqrt(len(plain)))
    t_comp = compensated.mean(0) / (compensated.std(0) / np.sqrt(len(compensated)))
    assert t_plain[0] < -4
    assert np.all(np.abs(t_comp) < 3)
    assert abs(compensated.mean(0)[0]) < 0.25 * abs(plain.mean(0)[0])


def test_discount_follows_the_deferred_recursion():
    """With a random walk Q: d_k = P_k (P_(k-1) + Q)^-1 d_(k-1) - P_k s_k, term by term (the
    slopes zero, so that the sum is evaluated anywhere)."""
    rng = np.random.default_rng(5)
    compensation, d = DeferredCompensation(), np.zeros(10)
    cov, walk = np.eye(10), 0.1 * np.eye(10)
    for _ in range(5):
        score = rng.standard_normal(10)
        root = rng.standard_normal((10, 10))
        after = np.linalg.inv(np.linalg.inv(cov + walk) + root @ root.T)
        compensation.add((score, np.zeros((10, 10)), np.zeros(10)), cov, walk)
        d = after @ np.linalg.solve(cov + walk, d) - after @ score
        cov = after
        np.testing.assert_allclose(compensation.offset(TRUTH, cov), d, atol=1e-12)


def test_compensation_needs_no_window():
    from astrocargo.envs.world import World
    from astrocargo.estimator.cargo_estimator import CargoEstimator

    with pytest.raises(ValueError, match="bias_compensation"):
        CargoEstimator(
            World(2).robot_model(0), 0, [1], 0.016, over_time_window=2, bias_compensation=True
        )
