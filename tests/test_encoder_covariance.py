"""The reported covariance with the encoders' noise correlated over updates
(``estimator.encoder_covariance``) against a Monte Carlo of the filter."""

import numpy as np
from scipy.linalg import expm

from astrocargo.estimator.encoder_covariance import EncoderCovariance
from astrocargo.estimator.ukf import InertialParamUKF

TRUTH = np.array([1.0, 0.05, -0.02, 0.03, 0.1, 0.12, 0.08, 0.01, 0.0, -0.01])
N_JOINTS, N_LAGS = 2, 30


def test_sandwich_matches_the_filters_spread():
    """Modes u_t = B u_t-1 + w_t per channel (stationary covariance I, Gm(L) = (B^L)^T, not
    symmetric) in the residual of every update, at R = E E^T + white (the per-update
    covariance), the regressor and the map slow: over 400 flights of 60 updates the filter's
    NEES is far from 10 with P (32), and within its Monte Carlo error of 10 with P + P X P."""
    rng = np.random.default_rng(2)
    skew = rng.standard_normal((8, 8))
    step = 0.8 * expm(0.03 * (skew - skew.T))  # a slow rotation
    lag_cov = np.stack([np.linalg.matrix_power(step, lag).T for lag in range(N_LAGS + 1)])
    prior = np.array([2.0, 0, 0, 0, 0.3, 0.3, 0.3, 0, 0, 0])
    nees_plain, nees_sandwich = [], []
    for _ in range(400):
        ukf = InertialParamUKF(prior, 100.0 * np.eye(10), np.zeros((10, 10)))
        cov_over_time = EncoderCovariance(lag_cov, slice(0, 8 * N_JOINTS), N_JOINTS)
        u = rng.standard_normal((N_JOINTS, 8))
        y_slow = rng.standard_normal((6, 10)) + 2.0 * np.eye(6, 10)
        balance_slow = 0.7 * rng.standard_normal((6, 8 * N_JOINTS))
        for k in range(60):
            u = u @ step.T + np.sqrt(1 - 0.8**2) * rng.standard_normal((N_JOINTS, 8))
            y = y_slow + 0.5 * rng.standard_normal((6, 10))
            balance = balance_slow + 0.2 * rng.standard_normal((6, 8 * N_JOINTS))
            cov = balance @ balance.T + 0.1 * np.eye(6)
            b = rng.standard_normal(6)
            z = y @ TRUTH + b - balance @ u.reshape(-1) + np.sqrt(0.1) * rng.standard_normal(6)
            ukf.predict()
            assert ukf.update_linear(z, y, b, cov).accepted
            cov_over_time.add(k, y, cov, balance)
        err = ukf.x - TRUTH
        nees_plain.append(err @ np.linalg.solve(ukf.P, err))
        nees_sandwich.append(err @ np.linalg.solve(cov_over_time.covariance(ukf.P), err))
    stderr = np.std(nees_sandwich) / np.sqrt(len(nees_sandwich))
    assert abs(np.mean(nees_sandwich) - 10) < 3 * stderr
    assert abs(np.mean(nees_plain) - 10) > 8 * stderr
