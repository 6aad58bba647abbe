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


def test_estimator_reports_leave_the_filters_path():
    """``bias_compensation`` and ``encoders_over_time`` move only what is reported: the filter's
    x and P are those of the estimator without them, bit for bit; the reported mean and
    covariance differ from them, and the reported spread follows the reported covariance."""
    from test_estimator import simulate

    kwargs = {"process_std_rel": 0.0, "encoders_over_time": False}
    reports = {**kwargs, "bias_compensation": True, "encoders_over_time": True}
    _, plain = simulate(2, "nominal", 20.0, "figure8_tumble", estimator_kwargs=kwargs)
    world, both = simulate(2, "nominal", 20.0, "figure8_tumble", estimator_kwargs=reports)
    for est, ref in zip(both, plain, strict=True):
        assert est.ukf.n_updates > 50
        np.testing.assert_array_equal(est.ukf.x, ref.ukf.x)
        np.testing.assert_array_equal(est.ukf.P, ref.ukf.P)
        np.testing.assert_array_equal(ref.params_cov(), ref.ukf.P)
        assert not np.allclose(est.params_mean(), ref.params_mean(), rtol=0, atol=1e-12)
        assert not np.allclose(est.params_cov(), est.ukf.P, rtol=1e-9, atol=0)
        assert np.all(np.linalg.eigvalsh(est.params_cov()) > 0)
        np.testing.assert_allclose(est.params_std(), np.sqrt(np.diag(est.params_cov())))
        assert np.all(est.physical_estimate()[1] != ref.physical_estimate()[1])


def test_default_reports_the_encoders_correlation_where_it_holds():
    """By default (``encoders_over_time=None``) the estimator reports P + P X P without a window
    and a random walk, and its filter's P with either; asked for (True) with a window or a walk
    it raises."""
    import pytest
    from test_estimator import simulate

    _, plain = simulate(1, "nominal", 12.0, "figure8_tumble")
    _, walk = simulate(1, "nominal", 12.0, "figure8_tumble",
                       estimator_kwargs={"process_std_rel": 1e-5})  # fmt: skip
    _, window = simulate(1, "nominal", 12.0, "figure8_tumble",
                         estimator_kwargs={"over_time_window": 8})  # fmt: skip
    est = plain[0]
    assert est.ukf.n_updates > 10
    assert est._reports is not None and est._reports.encoder_cov is not None
    assert not np.allclose(est.params_cov(), est.ukf.P, rtol=1e-9, atol=0)
    for other in (walk[0], window[0]):
        assert other.ukf.n_updates > 10
        np.testing.assert_array_equal(other.params_cov(), other.ukf.P)
    for demand in ({"process_std_rel": 1e-5}, {"over_time_window": 8}):
        with pytest.raises(ValueError, match="encoders_over_time|over_time_window"):
            simulate(1, "nominal", 1.0, "figure8_tumble",
                     estimator_kwargs={**demand, "encoders_over_time": True})  # fmt: skip
