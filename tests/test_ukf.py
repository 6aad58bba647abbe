"""Tests of estimator.ukf: agreement with filterpy's stock UKF and with a linear Kalman filter,
robustness (non-finite inputs, shapes, gating, positive definiteness) and the inertial filter."""

import math
import warnings

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter, unscented_transform
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, multivariate_normal

from astrocargo.estimator import constrained as constrained_module
from astrocargo.estimator.inertia import (
    log_cholesky_to_params,
    params_from_mass_com_inertia,
    params_to_log_cholesky,
    project_physical,
)
from astrocargo.estimator.ukf import (
    BatchedUKF,
    InertialParamUKF,
    LogCholeskyUKF,
    UpdateResult,
    constrained_mode,
    linear_params_hx,
)

TOL = 1e-9
DIM_X = 10
DIM_Z = 6

# A cargo box of 3 kg, centre of mass off the origin, rotated principal axes.
TRUE_MASS_KG = 3.0
TRUE_COM_M = np.array([0.05, -0.02, 0.10])
TRUE_AXES = Rotation.from_rotvec(0.7 * np.array([1.0, 2.0, 0.5]) / np.sqrt(5.25)).as_matrix()


def pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    """(..., 4, 4) pseudo-inertia J = [[0.5 tr(I) 1 - I, h], [h^T, m]] of (..., 10) parameters."""
    pi = np.asarray(pi)
    m, h = pi[..., 0], pi[..., 1:4]
    ixx, iyy, izz, ixy, ixz, iyz = np.moveaxis(pi[..., 4:], -1, 0)
    inertia = np.stack(
        [
            np.stack([ixx, ixy, ixz], -1),
            np.stack([ixy, iyy, iyz], -1),
            np.stack([ixz, iyz, izz], -1),
        ],
        -2,
    )
    trace = ixx + iyy + izz
    J = np.zeros(pi.shape[:-1] + (4, 4))
    J[..., :3, :3] = 0.5 * trace[..., None, None] * np.eye(3) - inertia
    J[..., :3, 3] = h
    J[..., 3, :3] = h
    J[..., 3, 3] = m
    return J


def is_physically_consistent(pi: np.ndarray) -> np.ndarray:
    """True where the body is realisable: pseudo-inertia positive definite."""
    return np.linalg.eigvalsh(pseudo_inertia(pi)).min(axis=-1) > 0.0


TRUE_PARAMS = params_from_mass_com_inertia(
    TRUE_MASS_KG,
    TRUE_COM_M,
    TRUE_AXES @ np.diag([0.02, 0.03, 0.04]) @ TRUE_AXES.T,
)
WRONG_PRIOR = params_from_mass_com_inertia(1.5, np.zeros(3), np.diag([0.01, 0.01, 0.01]))


def random_measurement(rng: np.random.Generator, m: int = DIM_Z):
    A = rng.normal(size=(m, DIM_X))
    b = rng.normal(scale=0.1, size=m)
    return A, b


def inertial_hx_batch(A: np.ndarray, b: np.ndarray):
    # Written out here rather than taken from ukf.linear_params_hx, so the comparison with the
    # stock filter does not rest on the module under test.
    return lambda sigmas: log_cholesky_to_params(sigmas) @ A.T + b


# --- checks of the test helpers themselves ---------------------------------------------------


def test_consistency_check_rejects_triangle_violation():
    # I_c = diag(1, 1, 2.5) is positive definite but breaks 1 + 1 >= 2.5 (the principal moments'
    # triangle inequality).
    bad = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    assert not is_physically_consistent(bad)
    assert is_physically_consistent(TRUE_PARAMS)
    assert is_physically_consistent(WRONG_PRIOR)


# --- agreement with filterpy and with a linear Kalman filter ----------------------------------


def make_stock_ukf(x0, P0, Q, alpha, beta, kappa, dim_z=DIM_Z):
    points = MerweScaledSigmaPoints(len(x0), alpha=alpha, beta=beta, kappa=kappa)
    stock = UnscentedKalmanFilter(
        dim_x=len(x0), dim_z=dim_z, dt=1.0, hx=None, fx=lambda x, dt: x, points=points
    )
    stock.x = x0.copy()
    stock.P = P0.copy()
    stock.Q = Q.copy()
    return stock


def assert_state_close(x, P, x_ref, P_ref):
    np.testing.assert_allclose(x, x_ref, rtol=TOL, atol=TOL * (1.0 + np.abs(x_ref).max()))
    np.testing.assert_allclose(P, P_ref, rtol=TOL, atol=TOL * np.abs(P_ref).max())


@pytest.mark.parametrize("via_update_linear", [False, True])
@pytest.mark.parametrize("alpha, kappa", [(0.5, 0.0), (1.0, 0.0), (0.8, 3.0 - DIM_X)])
def test_matches_filterpy_stock_ukf_on_inertial_map(alpha, kappa, via_update_linear):
    rng = np.random.default_rng(1)
    beta = 2.0
    x0 = params_to_log_cholesky(WRONG_PRIOR)
    P0 = np.diag(np.full(DIM_X, 0.3**2))
    Q = np.diag(np.full(DIM_X, 1e-3**2))
    if via_update_linear:
        ours = LogCholeskyUKF(WRONG_PRIOR, 0.3, 1e-3, alpha=alpha, beta=beta, kappa=kappa)
        np.testing.assert_array_equal(ours.x, x0)
        np.testing.assert_allclose(ours.P, P0, rtol=1e-15)
        np.testing.assert_allclose(ours.Q, Q, rtol=1e-15)
    else:
        ours = BatchedUKF(DIM_X, DIM_Z, x0, P0, Q, alpha=alpha, beta=beta, kappa=kappa)
    stock = make_stock_ukf(x0, P0, Q, alpha, beta, kappa)
    n_accepted = 0
    for _ in range(50):
        A, b = random_measurement(rng)
        R = np.diag(rng.uniform(0.01, 0.05, DIM_Z))
        z = A @ TRUE_PARAMS + b + rng.normal(size=DIM_Z) * np.sqrt(np.diag(R))
        hx_batch = inertial_hx_batch(A, b)

        ours.predict()
        stock.predict()
        assert_state_close(ours.x, ours.P, stock.x, stock.P)

        if via_update_linear:
            result = ours.update_linear(z, A, b, R)
        else:
            result = ours.update(z, hx_batch, R)
        stock.update(z, R=R, hx=lambda x, hb=hx_batch: hb(x[None])[0])
        n_accepted += result.accepted
        assert_state_close(ours.x, ours.P, stock.x, stock.P)
        for ours_value, stock_value in [(ours.K, stock.K), (ours.y, stock.y), (ours.S, stock.S)]:
            np.testing.assert_allclose(
                ours_value, stock_value, rtol=TOL, atol=TOL * np.abs(stock_value).max()
            )
        assert result.nis == pytest.approx(stock.y @ stock.SI @ stock.y, rel=TOL)
        assert ours.log_likelihood == pytest.approx(stock.log_likelihood, rel=TOL)
    assert n_accepted == 50 == ours.n_updates
    # The run must have moved the filter, or agreement would prove little.
    assert np.abs(ours.x - x0).max() > 0.1
    assert np.trace(ours.P) < 0.5 * np.trace(P0)


def test_two_updates_after_one_predict_match_filterpy_with_redrawn_points():
    # filterpy reuses the sigma points drawn in predict unless compute_process_sigmas redraws
    # them; BatchedUKF always draws them from the current (x, P).
    rng = np.random.default_rng(6)
    x0 = params_to_log_cholesky(WRONG_PRIOR)
    P0 = np.diag(np.full(DIM_X, 0.2**2))
    Q = np.diag(np.full(DIM_X, 1e-3**2))
    ours = BatchedUKF(DIM_X, DIM_Z, x0, P0, Q)
    stock = make_stock_ukf(x0, P0, Q, 0.5, 2.0, 0.0)
    ours.predict()
    stock.predict()
    for k in range(2):
        A, b = random_measurement(rng)
        R = 0.02 * np.eye(DIM_Z)
        z = A @ TRUE_PARAMS + b
        hx_batch = inertial_hx_batch(A, b)
        if k > 0:
            stock.compute_process_sigmas(dt=1.0)
        assert ours.update(z, hx_batch, R).accepted
        stock.update(z, R=R, hx=lambda x, hb=hx_batch: hb(x[None])[0])
        assert_state_close(ours.x, ours.P, stock.x, stock.P)


def test_measurement_moments_equal_filterpy_unscented_transform():
    rng = np.random.default_rng(7)
    ukf = LogCholeskyUKF(WRONG_PRIOR, prior_std_eta=0.3, process_std_eta=1e-3)
    A, b = random_measurement(rng)
    R = np.diag(rng.uniform(0.01, 0.05, DIM_Z))
    z = A @ TRUE_PARAMS + b
    ukf.predict()
    sigmas = ukf.sigma_points()
    assert ukf.update_linear(z, A, b, R).accepted
    np.testing.assert_array_equal(ukf.sigmas, sigmas)
    np.testing.assert_allclose(ukf.sigmas_h, log_cholesky_to_params(sigmas) @ A.T + b, rtol=1e-14)
    z_pred, S = unscented_transform(ukf.sigmas_h, ukf.Wm, ukf.Wc, R)
    np.testing.assert_allclose(ukf.S, S, rtol=1e-12)
    np.testing.assert_allclose(ukf.y, z - z_pred, rtol=1e-12, atol=1e-12 * np.abs(z).max())
    assert ukf.log_likelihood == pytest.approx(
        multivariate_normal(mean=np.zeros(DIM_Z), cov=S).logpdf(z - z_pred), rel=1e-12
    )


def test_predict_adds_process_noise():
    ukf, _, _ = linear_filter()
    P_before = ukf.P.copy()
    ukf.predict()
    np.testing.assert_array_equal(ukf.P, P_before + 1e-4 * np.eye(DIM_X))
    Q = np.diag(np.arange(1.0, DIM_X + 1.0))
    ukf.predict(Q)
    np.testing.assert_allclose(ukf.P, P_before + 1e-4 * np.eye(DIM_X) + Q, rtol=1e-15)
    np.testing.assert_array_equal(ukf.x, np.zeros(DIM_X))


def linear_kalman_step(x, P, z, H, R, Q):
    P = P + Q
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    x = x + K @ (z - H @ x)
    P = (np.eye(len(x)) - K @ H) @ P @ (np.eye(len(x)) - K @ H).T + K @ R @ K.T
    return x, P


def test_matches_linear_kalman_filter_on_linear_problem():
    rng = np.random.default_rng(2)
    x_true = rng.normal(size=DIM_X)
    x0 = np.zeros(DIM_X)
    G = rng.normal(size=(DIM_X, DIM_X))
    P0 = G @ G.T + 0.5 * np.eye(DIM_X)
    Q = np.diag(rng.uniform(1e-4, 1e-3, DIM_X))
    ours = BatchedUKF(DIM_X, DIM_Z, x0, P0, Q)
    x_ref, P_ref = x0.copy(), P0.copy()
    for _ in range(50):
        H = rng.normal(size=(DIM_Z, DIM_X))
        G = rng.normal(size=(DIM_Z, DIM_Z))
        R = 0.1 * G @ G.T + 0.01 * np.eye(DIM_Z)
        z = H @ x_true + rng.multivariate_normal(np.zeros(DIM_Z), R)
        ours.predict()
        result = ours.update(z, lambda sigmas, H=H: sigmas @ H.T, R)
        assert result.accepted and result.reason == "ok"
        x_ref, P_ref = linear_kalman_step(x_ref, P_ref, z, H, R, Q)
        assert_state_close(ours.x, ours.P, x_ref, P_ref)
    assert np.linalg.norm(ours.x - x_true) < 0.5


@settings(max_examples=50, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    alpha=st.floats(0.2, 1.0),
    kappa=st.sampled_from([0.0, 3.0 - DIM_X, 1.0]),
)
def test_sigma_points_match_filterpy(seed, alpha, kappa):
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(DIM_X, DIM_X))
    P = G @ G.T + 1e-3 * np.eye(DIM_X)
    x = rng.normal(scale=10.0, size=DIM_X)
    ukf = BatchedUKF(DIM_X, DIM_Z, x, P, np.eye(DIM_X), alpha=alpha, kappa=kappa)
    points = MerweScaledSigmaPoints(DIM_X, alpha=alpha, beta=2.0, kappa=kappa)
    ref = points.sigma_points(x, 0.5 * (P + P.T))
    np.testing.assert_allclose(ukf.sigma_points(), ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
    np.testing.assert_array_equal(ukf.Wm, points.Wm)
    np.testing.assert_array_equal(ukf.Wc, points.Wc)


# --- robustness ------------------------------------------------------------------------------


def linear_filter(gate_nis=None, seed=3):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(DIM_Z, DIM_X))
    ukf = BatchedUKF(
        DIM_X,
        DIM_Z,
        np.zeros(DIM_X),
        np.eye(DIM_X),
        1e-4 * np.eye(DIM_X),
        gate_nis=gate_nis,
    )
    return ukf, (lambda sigmas: sigmas @ H.T), 0.01 * np.eye(DIM_Z)


def assert_spd(P):
    np.testing.assert_array_equal(P, P.T)
    np.linalg.cholesky(P)


@pytest.mark.parametrize("bad_input", ["z", "R", "hx"])
@pytest.mark.parametrize("bad_value", [np.nan, np.inf])
def test_non_finite_input_skips_update(bad_input, bad_value):
    ukf, hx_batch, R = linear_filter()
    ukf.predict()
    ukf.update(np.ones(DIM_Z), hx_batch, R)
    ukf.predict()
    x_before, P_before = ukf.x.copy(), ukf.P.copy()
    z = np.ones(DIM_Z)
    if bad_input == "z":
        z[2] = bad_value
    elif bad_input == "R":
        R = R.copy()
        R[1, 1] = bad_value
    else:
        good_hx = hx_batch

        def hx_batch(sigmas):
            out = good_hx(sigmas)
            out[7, 3] = bad_value
            return out

    result = ukf.update(z, hx_batch, R)
    assert result == UpdateResult(False, "non-finite", result.nis)
    assert ukf.n_skipped_nonfinite == 1
    assert ukf.n_updates == 1
    np.testing.assert_array_equal(ukf.x, x_before)
    np.testing.assert_array_equal(ukf.P, P_before)
    assert_spd(ukf.P)


@pytest.mark.parametrize("bad_input", ["z", "R", "hx"])
def test_inf_input_is_skipped_without_warnings(bad_input):
    # A skipped update is not an error: no RuntimeWarning (inf times the zeros of the update's
    # constant matrices would give one through np.dot), so also none under warnings-as-errors.
    ukf, hx_batch, R = linear_filter()
    z = np.ones(DIM_Z)
    if bad_input == "z":
        z[0] = np.inf
    elif bad_input == "R":
        R = R.copy()
        R[0, 0] = np.inf
    else:
        good_hx = hx_batch

        def hx_batch(sigmas):
            out = good_hx(sigmas)
            out[3, 1] = -np.inf
            return out

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = ukf.update(z, hx_batch, R)
    assert result.reason == "non-finite" and ukf.n_skipped_nonfinite == 1


def test_wrong_shapes_raise_value_error():
    ukf, hx_batch, R = linear_filter()
    with pytest.raises(ValueError, match=r"z must have shape \(6,\)"):
        ukf.update(np.ones(DIM_Z + 1), hx_batch, R)
    with pytest.raises(ValueError, match=r"z must have shape \(6,\)"):
        ukf.update(np.ones((DIM_Z, 1)), hx_batch, R)
    with pytest.raises(ValueError, match=r"R must have shape \(6, 6\)"):
        ukf.update(np.ones(DIM_Z), hx_batch, np.eye(DIM_Z - 1))
    with pytest.raises(ValueError, match=r"hx_batch must return shape \(21, 6\)"):
        ukf.update(np.ones(DIM_Z), lambda s: hx_batch(s)[:, :5], R)
    with pytest.raises(ValueError, match=r"hx_batch must return shape \(21, 6\)"):
        ukf.update(np.ones(DIM_Z), lambda s: hx_batch(s)[0], R)
    with pytest.raises(ValueError, match=r"Q must have shape \(10, 10\)"):
        ukf.predict(np.eye(DIM_X - 1))
    with pytest.raises(ValueError, match=r"x0 must have shape \(10,\)"):
        BatchedUKF(DIM_X, DIM_Z, np.zeros(DIM_X - 1), np.eye(DIM_X), np.eye(DIM_X))
    with pytest.raises(ValueError, match="positive definite"):
        BatchedUKF(DIM_X, DIM_Z, np.zeros(DIM_X), -np.eye(DIM_X), np.eye(DIM_X))
    assert ukf.n_updates == 0


def test_gross_outlier_is_gated():
    gate = chi2.ppf(0.999, DIM_Z)
    ukf, hx_batch, R = linear_filter(gate_nis=gate)
    ukf.predict()
    result = ukf.update(np.zeros(DIM_Z), hx_batch, R)
    assert result.accepted and result.nis < gate
    ukf.predict()
    x_before, P_before = ukf.x.copy(), ukf.P.copy()
    result = ukf.update(np.full(DIM_Z, 1e3), hx_batch, R)
    assert not result.accepted and result.reason == "gated" and result.nis > gate
    assert ukf.n_gated == 1 and ukf.n_updates == 1
    np.testing.assert_array_equal(ukf.x, x_before)
    np.testing.assert_array_equal(ukf.P, P_before)
    # The same outlier passes when gating is off, or is turned off.
    ungated, hx_batch, R = linear_filter(gate_nis=None)
    ungated.predict()
    assert ungated.update(np.full(DIM_Z, 1e3), hx_batch, R).accepted
    assert ukf.gate_nis == gate
    ukf.gate_nis = None
    assert ukf.update(np.full(DIM_Z, 1e3), hx_batch, R).accepted
    with pytest.raises(ValueError, match="gate_nis"):
        ukf.gate_nis = -1.0


def _bumped_linear_hx(slope: float, bump: float):
    """1-D measurement that is linear except at the centre sigma point (index 0)."""

    def hx_batch(sigmas):
        out = slope * sigmas[:, :1]
        out[0] += bump
        return out

    return hx_batch


def test_non_positive_definite_posterior_is_rejected():
    # n = 1, P = 1, x = 0, beta = -10: Wm = (-3, 2, 2), Wc = (-12.25, 2, 2), sigma points
    # (0, 0.5, -0.5). With z = slope x plus a bump at the centre point, S = slope^2 - 160 bump^2 + R
    # and P_xz = slope, so for slope^2 > 160 bump^2 the posterior P - P_xz^2 / S is negative.
    ukf = BatchedUKF(1, 1, np.zeros(1), np.eye(1), np.zeros((1, 1)), beta=-10.0)
    result = ukf.update(np.array([0.3]), _bumped_linear_hx(20.0, 1.0), 1e-6 * np.eye(1))
    assert not result.accepted and result.reason == "not-positive-definite"
    assert ukf.S[0, 0] == pytest.approx(400.0 - 160.0 + 1e-6)  # S itself passed its check
    assert math.isfinite(result.nis)
    assert ukf.n_rejected_not_pd == 1 and ukf.n_updates == 0
    np.testing.assert_array_equal(ukf.P, np.eye(1))
    np.testing.assert_array_equal(ukf.x, np.zeros(1))
    # For slope^2 < 160 bump^2 the innovation covariance S is negative: rejected as well.
    result = ukf.update(np.array([0.3]), _bumped_linear_hx(10.0, 1.0), 1e-6 * np.eye(1))
    assert not result.accepted and result.reason == "not-positive-definite"
    assert math.isnan(result.nis)
    assert ukf.n_rejected_not_pd == 2
    np.testing.assert_array_equal(ukf.P, np.eye(1))
    # The same filter accepts a plain linear measurement.
    assert ukf.update(np.array([0.3]), _bumped_linear_hx(20.0, 0.0), np.eye(1)).accepted
    assert ukf.n_updates == 1


def test_posterior_is_symmetric_and_log_likelihood_finite():
    ukf, hx_batch, R = linear_filter()
    rng = np.random.default_rng(4)
    for _ in range(20):
        ukf.predict()
        assert ukf.update(rng.normal(size=DIM_Z), hx_batch, R).accepted
        assert_spd(ukf.P)
    assert math.isfinite(ukf.log_likelihood)


# --- inertial parameter filter: log-Cholesky state ------------------------------------------


def test_log_cholesky_filter_converges_with_consistent_sigma_points():
    rng = np.random.default_rng(5)
    # Prior std in eta: alpha and d are logs (0.5 is a factor e^0.5), s and t are lengths in m.
    prior_std_eta = np.array([0.5, 0.5, 0.5, 0.5, 0.05, 0.05, 0.05, 0.1, 0.1, 0.1])
    ukf = LogCholeskyUKF(WRONG_PRIOR, prior_std_eta=prior_std_eta, process_std_eta=1e-6)
    np.testing.assert_allclose(ukf.params_mean(), WRONG_PRIOR, rtol=1e-12, atol=1e-14)
    # Noiseless z, but R stays well above zero: with R much tighter than the prior a single
    # unscented update of this nonlinear map overshoots and the filter can diverge.
    R = 1e-2 * np.eye(DIM_Z)
    n_sigma_checked = 0
    for _ in range(300):
        A, b = random_measurement(rng)
        z = A @ TRUE_PARAMS + b
        ukf.predict()
        assert ukf.update_linear(z, A, b, R).accepted
        pis = log_cholesky_to_params(ukf.sigmas)
        assert is_physically_consistent(pis).all()
        n_sigma_checked += len(pis)
    assert n_sigma_checked == 300 * 21
    assert ukf.n_updates == 300
    estimate = ukf.params_mean()
    assert is_physically_consistent(estimate)
    assert abs(estimate[0] - TRUE_MASS_KG) / TRUE_MASS_KG < 1e-3
    np.testing.assert_allclose(estimate, TRUE_PARAMS, rtol=0, atol=1e-2)
    # Consistent: the eta error is plausible under the filter's own covariance.
    eta_error = ukf.x - params_to_log_cholesky(TRUE_PARAMS)
    assert eta_error @ np.linalg.solve(ukf.P, eta_error) < chi2.ppf(0.999, DIM_X)
    assert is_physically_consistent(log_cholesky_to_params(ukf.sigma_points())).all()
    std = ukf.params_std()
    assert std.shape == (10,) and np.all(std < 1e-2)
    cov = ukf.params_cov()
    np.testing.assert_array_equal(cov, cov.T)


def test_log_cholesky_filter_reports_physical_units():
    ukf = LogCholeskyUKF(TRUE_PARAMS, prior_std_eta=0.05, process_std_eta=0.0)
    np.testing.assert_allclose(ukf.params_mean(), log_cholesky_to_params(ukf.x))
    cov = ukf.params_cov()
    assert cov.shape == (10, 10)
    assert np.linalg.eigvalsh(cov).min() > -1e-12 * np.abs(cov).max()
    # Mass = exp(2 alpha): with std 0.05 in alpha the mass std is close to 0.1 m.
    assert ukf.params_std()[0] == pytest.approx(0.1 * TRUE_MASS_KG, rel=0.05)


def test_log_cholesky_filter_input_checks():
    with pytest.raises(ValueError):
        LogCholeskyUKF(
            params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5])),
            prior_std_eta=0.1,
            process_std_eta=0.0,
        )
    with pytest.raises(ValueError, match="prior_std_eta"):
        LogCholeskyUKF(TRUE_PARAMS, prior_std_eta=0.0, process_std_eta=0.0)
    ukf = LogCholeskyUKF(TRUE_PARAMS, prior_std_eta=0.1, process_std_eta=0.0)
    with pytest.raises(ValueError, match=r"A must have shape \(6, 10\)"):
        ukf.update_linear(np.zeros(DIM_Z), np.zeros((DIM_Z, 9)), np.zeros(DIM_Z), np.eye(DIM_Z))
    with pytest.raises(ValueError, match=r"b must have shape \(6,\)"):
        ukf.update_linear(np.zeros(DIM_Z), np.zeros((DIM_Z, 10)), np.zeros(5), np.eye(DIM_Z))


# --- inertial parameter filter: standard-parameter state, constrained reports ----------------


def random_spd(rng: np.random.Generator, n: int = DIM_X, scale: float = 1.0) -> np.ndarray:
    G = rng.normal(size=(n, n))
    return scale * (G @ G.T / n + 0.1 * np.eye(n))


def test_inertial_filter_is_the_linear_kalman_filter():
    rng = np.random.default_rng(11)
    P0 = random_spd(rng, scale=0.05)
    Q = np.diag(rng.uniform(1e-8, 1e-7, DIM_X))
    ours = InertialParamUKF(WRONG_PRIOR, P0, Q)
    x_ref, P_ref = WRONG_PRIOR.copy(), P0.copy()
    for _ in range(50):
        A, b = random_measurement(rng)
        G = rng.normal(size=(DIM_Z, DIM_Z))
        R = 0.01 * G @ G.T + 1e-3 * np.eye(DIM_Z)
        z = A @ TRUE_PARAMS + b + rng.multivariate_normal(np.zeros(DIM_Z), R)
        ours.predict()
        assert ours.update_linear(z, A, b, R).accepted
        x_ref, P_ref = linear_kalman_step(x_ref, P_ref, z - b, A, R, Q)
        assert_state_close(ours.x, ours.P, x_ref, P_ref)
    assert np.abs(ours.x - TRUE_PARAMS).max() < 0.05


def test_inertial_filter_matches_filterpy_stock_ukf():
    rng = np.random.default_rng(12)
    P0 = random_spd(rng, scale=0.05)
    Q = 1e-8 * np.eye(DIM_X)
    ours = InertialParamUKF(WRONG_PRIOR, P0, Q)
    stock = make_stock_ukf(WRONG_PRIOR, P0, Q, 0.5, 2.0, 0.0)
    for _ in range(30):
        A, b = random_measurement(rng)
        R = np.diag(rng.uniform(0.01, 0.05, DIM_Z))
        z = A @ TRUE_PARAMS + b + rng.normal(size=DIM_Z) * np.sqrt(np.diag(R))
        ours.predict()
        stock.predict()
        assert ours.update_linear(z, A, b, R).accepted
        stock.update(z, R=R, hx=lambda x, A=A, b=b: A @ x + b)
        assert_state_close(ours.x, ours.P, stock.x, stock.P)


def mahalanobis(pi, mean, cov):
    d = pi - mean
    return float(d @ np.linalg.solve(cov, d))


def test_reported_estimate_is_the_state_when_consistent():
    rng = np.random.default_rng(13)
    ukf = InertialParamUKF(WRONG_PRIOR, random_spd(rng, scale=0.01), np.zeros((DIM_X, DIM_X)))
    ukf.x = TRUE_PARAMS.copy()
    np.testing.assert_array_equal(ukf.params_mean(), TRUE_PARAMS)
    np.testing.assert_array_equal(ukf.params_cov(), ukf.P)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_reported_estimate_is_the_constrained_mode(seed):
    """An inconsistent state (negative principal moment, or triangle inequality broken) is
    reported as the consistent body nearest in the posterior's metric: consistent, no farther
    than the eigenvalue-clipped pseudo-inertia, and locally optimal (no small consistent move
    gets closer)."""
    rng = np.random.default_rng(seed)
    inertia = np.diag(rng.uniform(0.01, 0.05, 3))
    inertia[0, 0] = inertia[1, 1] + inertia[2, 2] + rng.uniform(0.001, 0.02)  # triangle broken
    if rng.uniform() < 0.5:
        inertia[2, 2] = -rng.uniform(0.001, 0.01)  # not positive definite
    bad = params_from_mass_com_inertia(rng.uniform(1, 5), rng.normal(scale=0.1, size=3), inertia)
    assert not is_physically_consistent(bad)
    cov = random_spd(rng, scale=1e-3)
    ukf = InertialParamUKF(WRONG_PRIOR, cov, np.zeros((DIM_X, DIM_X)))
    ukf.x = bad
    mode = ukf.params_mean()
    assert is_physically_consistent(mode)
    d_mode = mahalanobis(mode, bad, cov)
    lam, vec = np.linalg.eigh(pseudo_inertia(bad))
    clipped_j = (vec * np.maximum(lam, 1e-3 * lam[-1])) @ vec.T
    clipped = np.concatenate(
        (
            [clipped_j[3, 3]],
            clipped_j[:3, 3],
            np.trace(clipped_j[:3, :3]) * np.ones(3) - np.diag(clipped_j[:3, :3]),
            -clipped_j[[0, 0, 1], [1, 2, 2]],
        )
    )
    assert is_physically_consistent(clipped)
    assert d_mode <= mahalanobis(clipped, bad, cov) * (1 + 1e-9)
    eta = params_to_log_cholesky(mode)
    for _ in range(50):
        nearby = log_cholesky_to_params(eta + 1e-3 * rng.normal(size=DIM_X))
        assert mahalanobis(nearby, bad, cov) >= d_mode * (1 - 1e-6)
    # Cached until the state changes.
    np.testing.assert_array_equal(ukf.params_mean(), mode)
    again, solved = constrained_mode(bad, cov)
    assert solved
    np.testing.assert_array_equal(again, mode)
    assert ukf.n_mode_fallbacks == 0


def test_reported_estimate_follows_every_change_of_x_and_p():
    """The cached report is made again whenever x or P changes: in place, by assignment or by a
    pending predict (its P + Q), and each time equals the constrained mode of the new (x, P)."""
    rng = np.random.default_rng(15)
    inertia = np.diag([0.02, 0.03, 0.04])
    inertia[0, 0] = inertia[1, 1] + inertia[2, 2] + 0.01  # triangle broken: x is not the mode
    bad = params_from_mass_com_inertia(2.0, np.array([0.05, -0.02, 0.03]), inertia)
    walk = random_spd(rng, scale=1e-4)
    ukf = InertialParamUKF(WRONG_PRIOR, random_spd(rng, scale=1e-3), walk)
    ukf.x = bad
    reports = [ukf.params_mean()]

    def check_new_report() -> None:
        mode = ukf.params_mean()
        np.testing.assert_array_equal(mode, constrained_mode(ukf.x, ukf.P, start=reports[-1])[0])
        assert not any(np.array_equal(mode, earlier) for earlier in reports)
        reports.append(mode)

    ukf.P[0, 0] *= 4.0  # P in place
    check_new_report()
    ukf.x[4] += 0.002  # x in place
    check_new_report()
    ukf.predict()  # P + Q, made when P is read
    check_new_report()
    ukf.P = ukf.P * 0.5
    check_new_report()
    np.testing.assert_array_equal(ukf.params_mean(), reports[-1])  # nothing changed: cached


def test_physical_estimate_propagates_the_posterior():
    rng = np.random.default_rng(14)
    cov = random_spd(rng, scale=1e-6)
    ukf = InertialParamUKF(TRUE_PARAMS, cov, np.zeros((DIM_X, DIM_X)))
    mean, std = ukf.physical_estimate()
    assert mean[0] == pytest.approx(TRUE_MASS_KG)
    np.testing.assert_allclose(mean[1:4], TRUE_COM_M, rtol=1e-12)
    assert std[0] == pytest.approx(np.sqrt(cov[0, 0]), rel=1e-6)
    # Monte Carlo of the same (tight, so nearly linear) posterior.
    samples = rng.multivariate_normal(TRUE_PARAMS, cov, size=20000)
    com = samples[:, 1:4] / samples[:, :1]
    np.testing.assert_allclose(std[1:4], com.std(axis=0), rtol=0.05)


def test_inertial_filter_input_checks():
    bad = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    with pytest.raises(ValueError, match="physically consistent"):
        InertialParamUKF(bad, np.eye(DIM_X), np.zeros((DIM_X, DIM_X)))
    with pytest.raises(ValueError, match="P0"):
        InertialParamUKF(TRUE_PARAMS, -np.eye(DIM_X), np.zeros((DIM_X, DIM_X)))
    ukf = InertialParamUKF(TRUE_PARAMS, np.eye(DIM_X), np.zeros((DIM_X, DIM_X)))
    with pytest.raises(ValueError, match=r"A must have shape \(6, 10\)"):
        ukf.update_linear(np.zeros(DIM_Z), np.zeros((DIM_Z, 9)), np.zeros(DIM_Z), np.eye(DIM_Z))


def test_constrained_mode_falls_back_to_a_consistent_body():
    """A covariance that is not positive definite cannot whiten the distance: the report falls
    back to the eigenvalue-clipped body (consistent), says so, and nothing raises."""
    bad = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    mode, solved = constrained_mode(bad, -np.eye(DIM_X))
    assert not solved and is_physically_consistent(mode)
    ukf = InertialParamUKF(TRUE_PARAMS, np.eye(DIM_X), np.zeros((DIM_X, DIM_X)))
    ukf.x, ukf.P = bad, np.diag(np.r_[np.ones(9), 0.0])
    assert is_physically_consistent(ukf.params_mean())
    assert ukf.n_mode_fallbacks == 1


# --- the one update path against plain references --------------------------------------------


def reference_update(x, P, z, hx_batch, R, alpha, beta, kappa, gate_nis):
    """filterpy's update written out with numpy (sigma points, filterpy's unscented_transform,
    K = P_xz S^-1, x + K y, P - K S K^T), with the outcomes of `BatchedUKF.update`. Returns
    (reason, x, P, y, S, K, nis)."""
    n = len(x)
    points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    if not np.isfinite(R).all():
        return "non-finite", x, P, None, None, None, math.nan
    try:
        sigmas = points.sigma_points(x, P)
    except np.linalg.LinAlgError:
        return "not-positive-definite", x, P, None, None, None, math.nan
    sigmas_h = hx_batch(sigmas)
    if not np.isfinite(sigmas_h).all():
        return "non-finite", x, P, None, None, None, math.nan
    z_pred, S = unscented_transform(sigmas_h, points.Wm, points.Wc, R)
    P_xz = (points.Wc[:, None] * (sigmas - x)).T @ (sigmas_h - z_pred)
    if np.linalg.eigvalsh(S).min() <= 0.0:
        return "not-positive-definite", x, P, None, None, None, math.nan
    K = np.linalg.solve(S, P_xz.T).T
    y = z - z_pred
    with np.errstate(invalid="ignore"):  # NaN in z
        nis = float(y @ np.linalg.solve(S, y))
    if not math.isfinite(nis):
        reason = "non-finite" if not np.isfinite(z).all() else "not-positive-definite"
        return reason, x, P, y, S, K, nis
    if gate_nis is not None and nis > gate_nis:
        return "gated", x, P, y, S, K, nis
    P_post = P - K @ S @ K.T
    if np.linalg.eigvalsh(0.5 * (P_post + P_post.T)).min() <= 0.0:
        return "not-positive-definite", x, P, y, S, K, nis
    return "ok", x + K @ y, P_post, y, S, K, nis


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    dims=st.sampled_from([(10, 6), (3, 2), (1, 1), (2, 5)]),
    alpha_kappa=st.sampled_from([(0.5, 0.0), (1.0, 0.0), (0.8, 1.0), (0.3, 2.0)]),
    beta=st.sampled_from([2.0, 0.0]),
)
def test_update_matches_a_plain_reference_on_every_outcome(seed, dims, alpha_kappa, beta):
    """The compiled update (sigma points -> transform -> gain through the Cholesky factor of S)
    against filterpy's equations written out with numpy, on a mildly nonlinear measurement and
    on every outcome: accepted, non-finite input, gated, S not positive definite."""
    rng = np.random.default_rng(seed)
    n, m = dims
    alpha, kappa = alpha_kappa
    gate = chi2.ppf(0.999, m)
    ukf = BatchedUKF(
        n, m, rng.normal(scale=3.0, size=n), random_spd(rng, n), 1e-3 * np.eye(n),
        alpha=alpha, beta=beta, kappa=kappa, gate_nis=gate,
    )  # fmt: skip
    reasons = set()
    for k in range(15):
        H = rng.normal(size=(m, n))
        # Mildly nonlinear, but the first update is linear and clean, so that the accepted path
        # is always exercised: drawn at random, every outcome can miss it (with alpha 0.5 the
        # centre weight is negative and a nonlinear S may not be positive definite).
        bend = 0.3 if k else 0.0

        def hx_batch(sigmas, H=H, bend=bend):
            return sigmas @ H.T + bend * np.sin(sigmas[:, :1])

        G = rng.normal(size=(m, m))
        R = 0.05 * G @ G.T + 1e-2 * np.eye(m)
        z = hx_batch(ukf.x[None])[0] + np.linalg.cholesky(R) @ rng.normal(size=m)
        case = rng.integers(8) if k else 7  # 4..7: a clean draw
        if case == 0:
            z[rng.integers(m)] = rng.choice([np.nan, np.inf])
        elif case == 1:
            R[rng.integers(m), rng.integers(m)] = np.nan
        elif case == 2:
            z = z + 1e3
        elif case == 3:
            R = -R
        ukf.predict()
        x, P = ukf.x.copy(), ukf.P.copy()
        reason, x_ref, P_ref, y, S, K, nis = reference_update(
            x, P, z, hx_batch, R, alpha, beta, kappa, gate
        )
        result = ukf.update(z, hx_batch, R)
        reasons.add(reason)
        assert (result.accepted, result.reason) == (reason == "ok", reason)
        assert_state_close(ukf.x, ukf.P, x_ref, P_ref)
        np.testing.assert_array_equal(ukf.P, ukf.P.T)
        if y is not None and math.isfinite(nis):
            assert result.nis == pytest.approx(nis, rel=TOL)
            for ours, ref in [(ukf.y, y), (ukf.S, S), (ukf.K, K)]:
                np.testing.assert_allclose(ours, ref, rtol=TOL, atol=TOL * np.abs(ref).max())
            log_likelihood = multivariate_normal(mean=np.zeros(m), cov=S).logpdf(y)
            assert ukf.log_likelihood == pytest.approx(log_likelihood, rel=TOL)
    counted = ukf.n_updates + ukf.n_skipped_nonfinite + ukf.n_gated + ukf.n_rejected_not_pd
    assert counted == 15
    assert "ok" in reasons


def test_predict_is_made_before_the_next_update_or_when_P_is_read():
    """`predict` marks P += Q; the next compiled update makes it first, in order with any other
    predict, and reading or assigning P settles it."""
    rng = np.random.default_rng(31)
    P0 = random_spd(rng, scale=0.05)
    Q = np.diag(rng.uniform(1e-4, 1e-3, DIM_X))
    A, b = random_measurement(rng)
    R = 0.01 * np.eye(DIM_Z)
    z = A @ TRUE_PARAMS + b
    ours = InertialParamUKF(WRONG_PRIOR, P0, Q)
    ours.predict()
    ours.predict()
    assert ours.update_linear(z, A, b, R).accepted
    x_ref, P_ref = linear_kalman_step(WRONG_PRIOR, (P0 + Q) + Q, z - b, A, R, np.zeros_like(Q))
    assert_state_close(ours.x, ours.P, x_ref, P_ref)
    P_updated = ours.P.copy()
    ours.predict()
    np.testing.assert_array_equal(ours.P, P_updated + Q)
    np.testing.assert_array_equal(ours.P, P_updated + Q)  # made once
    ours.predict()
    ours.P = P0  # an assignment replaces P, predicted or not
    np.testing.assert_array_equal(ours.P, P0)
    assert ours.update_linear(z, A, b, R).accepted
    x_ref, P_ref = linear_kalman_step(x_ref, P0, z - b, A, R, np.zeros_like(Q))
    assert_state_close(ours.x, ours.P, x_ref, P_ref)


def test_update_linear_takes_any_float_arrays():
    """Lists and non-contiguous arrays are converted (the compiled call takes
    C-contiguous float64 arrays) and give the same update; wrong shapes raise ValueError."""
    rng = np.random.default_rng(32)
    A, b = random_measurement(rng)
    R = np.diag(rng.uniform(0.01, 0.05, DIM_Z))
    z = A @ TRUE_PARAMS + b
    plain = InertialParamUKF(WRONG_PRIOR, random_spd(rng, scale=0.05), 1e-8 * np.eye(DIM_X))
    other = InertialParamUKF(WRONG_PRIOR, plain.P.copy(), plain.Q.copy())
    assert plain.update_linear(z, A, b, R).accepted
    A_fortran = np.asfortranarray(A)
    R_strided = np.zeros((DIM_Z, 2 * DIM_Z))
    R_strided[:, ::2] = R
    assert other.update_linear(
        z.tolist(), A_fortran, np.repeat(b, 2)[::2], R_strided[:, ::2]
    ).accepted
    np.testing.assert_array_equal(other.x, plain.x)
    np.testing.assert_array_equal(other.P, plain.P)
    with pytest.raises(ValueError, match=r"z must have shape \(6,\)"):
        plain.update_linear(np.zeros(DIM_Z + 1), A, b, R)
    with pytest.raises(ValueError, match=r"R must have shape \(6, 6\)"):
        plain.update_linear(z, A, b, np.eye(DIM_Z - 1))
    plain.predict()
    P_predicted = plain._P + plain.Q  # (the predict is made by the next update)
    with pytest.raises(ValueError, match=r"b must have shape \(6,\)"):
        plain.update_linear(z, A, b.tolist()[:5], R)
    assert plain.n_updates == 1
    np.testing.assert_array_equal(plain.P, P_predicted)  # a rejected call keeps the predict


def test_linear_params_hx_maps_one_point_or_many():
    rng = np.random.default_rng(21)
    A, b = random_measurement(rng)
    hx = linear_params_hx(A, b, None)
    points = rng.normal(size=(21, DIM_X))
    np.testing.assert_allclose(hx(points), points @ A.T + b, rtol=1e-14)
    np.testing.assert_allclose(hx(points[3]), A @ points[3] + b, rtol=1e-14)


def inconsistent_body(rng: np.random.Generator) -> np.ndarray:
    inertia = np.diag(rng.uniform(0.01, 0.05, 3))
    inertia[0, 0] = inertia[1, 1] + inertia[2, 2] + rng.uniform(0.001, 0.02)
    if rng.uniform() < 0.5:
        inertia[2, 2] = -rng.uniform(0.001, 0.01)
    return params_from_mass_com_inertia(rng.uniform(1, 5), rng.normal(scale=0.1, size=3), inertia)


def reference_barrier_mode(mean, cov, start, gap=1e-4):
    """The barrier method of `constrained_mode` computed plainly: J from pi, its inverse,
    einsums, np.linalg.solve."""
    lower = np.linalg.cholesky(cov)
    basis = pseudo_inertia(np.eye(DIM_X))  # E_k = J(e_k)
    basis_l = np.einsum("kij,kl->lij", basis, lower)  # dJ / dv_l

    def barrier_terms(pi):
        """log det J, its gradient and (minus) Hessian in v; None where J is not definite."""
        j = pseudo_inertia(pi)
        try:
            chol = np.linalg.cholesky(j)
        except np.linalg.LinAlgError:
            return None
        a = np.einsum("ij,ljk->lik", np.linalg.inv(j), basis_l)  # J^-1 dJ/dv_l
        return (
            2.0 * np.log(np.diag(chol)).sum(),
            np.einsum("lii->l", a),
            np.einsum("lij,mji->lm", a, a),
        )

    clipped = project_physical(mean, min_eig=1e-3)
    v, t = np.linalg.solve(lower, clipped - mean), 1.0
    if start is not None:
        v_start = np.linalg.solve(lower, start - mean)
        if v_start @ v_start < v @ v:
            v, t = v_start, 1e-2
    terms = barrier_terms(mean + lower @ v)
    while True:
        for _ in range(50):
            log_det, grad_b, hess_b = terms
            grad = v - t * grad_b
            step = -np.linalg.solve(np.eye(DIM_X) + t * hess_b, grad)
            decrement = -grad @ step
            if decrement < 0.1 * gap:
                break
            value = 0.5 * v @ v - t * log_det
            scale = 1.0
            while scale > 1e-12:
                trial = v + scale * step
                trial_terms = barrier_terms(mean + lower @ trial)
                if trial_terms is not None:
                    if 0.5 * trial @ trial - t * trial_terms[0] <= value - 0.25 * scale * decrement:
                        break
                scale *= 0.5
            else:
                break
            v, terms = trial, trial_terms
        if 4.0 * t <= gap:
            break
        t = max(0.02 * t, 0.25 * gap)
    return mean + lower @ v


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), with_start=st.booleans())
def test_constrained_mode_follows_a_plain_barrier_computation(seed, with_start):
    """Where the iteration stops depends on its path (some 1e-6 relative from the exact
    minimiser of the last barrier problem), so the compiled Newton method must keep the path of
    the plain one step for step: both return the same body to rounding."""
    rng = np.random.default_rng(seed)
    bad = inconsistent_body(rng)
    cov = random_spd(rng, scale=10 ** rng.uniform(-5, -1))
    start = TRUE_PARAMS if with_start else None
    plain = reference_barrier_mode(bad, cov, start)
    mode, solved = constrained_mode(bad, cov, start=start)
    assert solved and is_physically_consistent(mode)
    np.testing.assert_allclose(mode, plain, rtol=TOL, atol=TOL * np.abs(plain).max())


def test_constrained_mode_reports_a_breakdown(monkeypatch):
    """Should the Newton iteration break down numerically, the report is the eigenvalue-clipped
    body (consistent), flagged as not solved and counted by the filter."""
    rng = np.random.default_rng(22)
    bad = inconsistent_body(rng)
    cov = random_spd(rng, scale=1e-3)
    mode, solved = constrained_mode(bad, cov)
    assert solved

    def broken(mean, lower, v, t, gap):
        return v, False

    monkeypatch.setattr(constrained_module, "barrier_newton", broken)
    mode, solved = constrained_mode(bad, cov)
    assert not solved and is_physically_consistent(mode)
    np.testing.assert_allclose(mode, project_physical(bad, min_eig=1e-3), rtol=1e-12)
    ukf = InertialParamUKF(TRUE_PARAMS, cov, np.zeros((DIM_X, DIM_X)))
    ukf.x = bad
    assert is_physically_consistent(ukf.params_mean())
    assert ukf.n_mode_fallbacks == 1


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_copied_filter_updates_its_own_buffer_like_the_original(how):
    """The filter's arrays are views of one buffer the kernels update in place: a copy must
    rebuild its views on its own buffer, then follow the original bit for bit."""
    import copy
    import pickle

    ukf, hx, R = linear_filter()
    rng = np.random.default_rng(9)
    ukf.predict()
    ukf.update(rng.normal(size=DIM_Z), hx, R)
    twin = copy.deepcopy(ukf) if how == "deepcopy" else pickle.loads(pickle.dumps(ukf))
    for _ in range(5):
        z = rng.normal(size=DIM_Z)
        for f in (ukf, twin):
            f.predict()
            f.update(z, hx, R)
        np.testing.assert_array_equal(twin.x, ukf.x)
        np.testing.assert_array_equal(twin.P, ukf.P)
    assert not np.shares_memory(twin.x, ukf.x)
    assert np.shares_memory(twin.x, twin._state) and np.shares_memory(twin.S, twin._state)


def test_same_values_agrees_with_array_equal():
    """The compiled check behind `params_mean`'s cache: np.array_equal's answer, None never."""
    from astrocargo.estimator.unscented import same_values

    a = np.arange(12.0).reshape(3, 4)
    changed = a.copy()
    changed[2, 3] += 1e-12
    with_nan = a.copy()
    with_nan[0, 0] = np.nan
    for other in (a.copy(), changed, with_nan, a[:2].copy(), -0.0 * a):
        assert same_values(a, other) == np.array_equal(a, other)
    assert not same_values(with_nan, with_nan.copy())
    assert not same_values(a, None)
    assert not same_values(a, changed)
