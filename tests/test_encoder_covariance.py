"""The reported covariance with the encoders' noise correlated over updates
(``estimator.encoder_covariance``) against a Monte Carlo of the filter."""

import numpy as np
import pytest
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


def plain_cross_terms(indices, vs, lag_cov):
    """X = sum_(k != l) V_k Gm(l - k) V_l^T per joint, Gm(-L) = Gm(L)^T, zero beyond n_lags:
    the definition, pair by pair (``vs`` (n, 10, nj, 8)); and the sum of the terms' sizes |.|
    entry by entry, the scale of the sum's rounding."""
    n_lags = lag_cov.shape[0] - 1
    X, size = np.zeros((10, 10)), np.zeros((10, 10))
    for k, (index_k, v_k) in enumerate(zip(indices, vs, strict=True)):
        for index_l, v_l in zip(indices[:k], vs[:k], strict=True):
            lag = index_k - index_l
            if lag <= n_lags:
                for c in range(v_k.shape[1]):
                    term = v_l[:, c] @ lag_cov[lag] @ v_k[:, c].T
                    X += term + term.T
                    size += np.abs(v_l[:, c]) @ np.abs(lag_cov[lag]) @ np.abs(v_k[:, c]).T
    return X, size + size.T


def assert_rounding(actual, plain):
    """Equal to the ``plain`` sum (X, sizes) to rounding: 1e-12 of the terms' sizes."""
    desired, size = plain
    assert np.all(np.abs(actual - desired) <= 1e-12 * size)


def _random_updates(rng, n, n_joints=N_JOINTS):
    """Y (6, 10), R (6, 6) and E (6, 8 nj) of ``n`` updates, and their V = Y^T R^-1 E."""
    updates = []
    for _ in range(n):
        y, e = rng.standard_normal((6, 10)), rng.standard_normal((6, 8 * n_joints))
        cov = e @ e.T + np.eye(6)
        v = (np.linalg.solve(cov, y).T @ e).reshape(10, n_joints, 8)
        updates.append((y, cov, e, v))
    return updates


def test_compiled_cross_terms_equal_the_definition():
    """``add`` (the ring and the compiled sum over lags) gives X as defined, to rounding, on
    random V's whose update counts have gaps (some pairs beyond n_lags) and a ring that wraps
    around several times; every step of the way, not only at the end."""
    rng = np.random.default_rng(5)
    n_lags, n_joints = 6, 3
    lag_cov = rng.standard_normal((n_lags + 1, 8, 8))  # not symmetric: Gm(-L) = Gm(L)^T
    indices = np.cumsum(rng.integers(1, 4, size=40))
    updates = _random_updates(rng, len(indices), n_joints)
    cross = EncoderCovariance(lag_cov, slice(0, 8 * n_joints), n_joints, rollback=2)
    for k, (index, (y, cov, e, _)) in enumerate(zip(indices, updates, strict=True)):
        cross.add(int(index), y, cov, e)
        vs = [u[3] for u in updates[: k + 1]]
        assert_rounding(cross.X, plain_cross_terms(indices[: k + 1], vs, lag_cov))
    assert np.abs(cross.X).max() > 1.0
    np.testing.assert_array_equal(cross.X, cross.X.T)


def test_state_restores_after_a_rollback():
    """After ``state``, up to ``rollback`` more updates, ``restore`` and the updates that follow,
    X equals that of a twin that never took the undone updates, bit for bit (and the
    definition); a rollback deeper than the ring keeps raises instead of pairing wrong V's."""
    rng = np.random.default_rng(6)
    lag_cov = rng.standard_normal((N_LAGS + 1, 8, 8))
    columns, depth = slice(0, 8 * N_JOINTS), 5
    updates = _random_updates(rng, 60)
    cross = EncoderCovariance(lag_cov, columns, N_JOINTS, rollback=depth)
    twin = EncoderCovariance(lag_cov, columns, N_JOINTS, rollback=depth)  # the same ring
    for index in range(40):
        cross.add(index, *updates[index][:3])
        twin.add(index, *updates[index][:3])
    saved = cross.state()
    for index in range(40, 40 + depth):  # undone: their V's differ from the ones that follow
        cross.add(index, *_random_updates(rng, 1)[0][:3])
    cross.restore(saved)
    np.testing.assert_array_equal(cross.X, twin.X)
    kept = list(range(40)) + list(range(42, 60))
    for index in kept[40:]:
        cross.add(index, *updates[index][:3])
        twin.add(index, *updates[index][:3])
        np.testing.assert_array_equal(cross.X, twin.X)
    assert_rounding(cross.X, plain_cross_terms(kept, [updates[k][3] for k in kept], lag_cov))
    saved = cross.state()
    for index in range(60, 61 + depth):
        cross.add(index, *updates[index - 60][:3])
    with pytest.raises(RuntimeError, match="rollback deeper"):
        cross.restore(saved)


def test_estimators_rollback_restores_its_cross_terms():
    """A rollback of a flying estimator (``CargoEstimator._roll_back``, as after a gated
    instant) restores X to the sum over the surviving updates' V's (the definition over the
    ones it recorded), and an update after it pairs with them alone."""
    from test_estimator import simulate

    taken = []
    add = EncoderCovariance.add

    def recording_add(self, index, regressor, cov, balance_map):
        v = np.linalg.solve(cov, regressor).T @ balance_map[:, self.columns]
        taken.append((index, v.reshape(10, self.n_joints, 8), (regressor, cov, balance_map)))
        add(self, index, regressor, cov, balance_map)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(EncoderCovariance, "add", recording_add)
        _, (est,) = simulate(1, "nominal", 12.0, "figure8_tumble")
    cross = est._reports.encoder_cov
    assert len(taken) == est.ukf.n_updates > 20
    before, gated = cross.X, est.stamp
    undone = [s[0] for s in est._snapshots if s[0] >= gated - est.rollback_steps]
    assert est._roll_back(gated) == len(undone) > 1
    kept = [t for t in taken if t[0] < undone[0] // est.update_every]
    assert len(taken) - len(undone) <= len(kept) < len(taken)
    indices, vs = [t[0] for t in kept], [t[1] for t in kept]
    assert not np.allclose(cross.X, before, rtol=1e-6, atol=0)
    assert_rounding(cross.X, plain_cross_terms(indices, vs, cross.lag_cov))
    index, v, inputs = taken[-1][0] + 1, taken[-1][1], taken[-1][2]
    cross.add(index, *inputs)
    assert_rounding(cross.X, plain_cross_terms([*indices, index], [*vs, v], cross.lag_cov))
