"""The measurement covariance's model (estimator/noise_model.py) and the colour of its sources."""

import numpy as np
import pytest

from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.motion import band_factors, condition_on_mismatch, filtered_motion_gains
from astrocargo.estimator.noise_model import NoiseModel, decorrelation_updates
from astrocargo.estimator.preprocess import StateVariableFilter

DT, PRE_HZ, SLOW_HZ, EVERY, UPDATE = 0.016, 1.0, 0.25, 2, 10


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def _filtered_sources(rng, n_rep: int, n_updates: int, std: np.ndarray) -> np.ndarray:
    """The estimator's chain on white noise: per replica 2 robots x (3 accelerometer-like values,
    3 gyro-like first derivatives), std ``std`` (2,) per sample; returns the filtered motion noise
    at the update instants (n_updates, n_rep, 12)."""
    n_ch = n_rep * 12
    rate = np.zeros(12, dtype=bool)
    rate[[3, 4, 5, 9, 10, 11]] = True
    rate = np.tile(rate, n_rep)
    pre = StateVariableFilter(n_ch, DT, PRE_HZ, held=slice(0, n_ch))
    slow = StateVariableFilter(n_ch, DT * EVERY, SLOW_HZ)
    scale = np.where(rate, std[1], std[0])
    out = np.empty((n_updates, n_ch))
    pre.step(np.zeros(n_ch))
    slow.step(np.zeros(n_ch))
    for k in range(1, n_updates * UPDATE + 1):
        y, yd, _ = pre.step(rng.normal(size=n_ch) * scale)
        if k % EVERY == 0:
            filtered, _, _ = slow.step(np.where(rate, yd, y))
            if k % UPDATE == 0:
                out[k // UPDATE - 1] = filtered
    return out.reshape(n_updates, n_rep, 12)


@pytest.mark.parametrize("use_colour", [True, False])
def test_conditioning_on_coloured_sources_is_never_overconfident(use_colour):
    """Monte Carlo on the estimator's filter chain: two robots, each an accelerometer-like white
    source (filtered value) and a gyro-like differentiated one (filtered derivative), a balance
    noise n and a mismatch d built from both. The updates' conditioned residuals r_k = n_k -
    E[n_k | d_k], summed over a long run (what a filter that treats updates as independent
    averages), must have a covariance no larger than the sum of the per-update Cov[n | d] with
    each source at its in-band level (band factors): conservative, and within a factor 1.6 where
    the white source dominates. Without the band factors (per-sample variances, colour ignored)
    the white source's residual is about ten times under-modelled and the check fails."""
    rng = np.random.default_rng(7)
    std = np.array([1e-3, 2e-4])
    gains = filtered_motion_gains(DT, PRE_HZ, SLOW_HZ, EVERY)[:2]
    factors = band_factors(np.append(gains, 1.0), DT, PRE_HZ, SLOW_HZ, UPDATE)[:2]
    var = np.repeat((std * gains) ** 2, 3)
    band = np.repeat(factors, 3) if use_colour else np.ones(6)
    noise_maps = [rng.normal(size=(6, 6)) for _ in range(2)]
    mismatch_maps = [-np.hstack([np.eye(3), 0.3 * rng.normal(size=(3, 3))])]
    mismatch_maps.append(np.hstack([np.eye(3), 0.3 * rng.normal(size=(3, 3))]))
    args = (noise_maps, mismatch_maps, [var, var])
    _, cov = condition_on_mismatch(*args, np.zeros(3), [band, band])
    gain = np.column_stack([condition_on_mismatch(*args, e, [band, band])[0] for e in np.eye(3)])
    n_rep, n_updates = 300, 400
    xi = _filtered_sources(rng, n_rep, n_updates, std)
    n = xi[..., :6] @ noise_maps[0].T + xi[..., 6:] @ noise_maps[1].T
    d = xi[..., :6] @ mismatch_maps[0].T + xi[..., 6:] @ mismatch_maps[1].T
    total = (n - d @ gain.T).sum(axis=0)  # (n_rep, 6)
    empirical = total.T @ total / n_rep
    claimed = n_updates * cov
    root = np.linalg.cholesky(np.linalg.inv(claimed))
    ratio = np.linalg.eigvalsh(root.T @ empirical @ root)
    if use_colour:
        assert ratio.max() < 1.3
        assert ratio.max() > 1 / 1.6
    else:
        assert ratio.max() > 3.0


def test_noise_model_is_the_estimator_s():
    """CargoEstimator's covariance pieces are its NoiseModel's; "none" is the scalar model."""
    robot = _robot()
    est = CargoEstimator(robot, 0, [1], 0.016, sensor_noise=(1e-3, 2e-4, 1e-3))
    model = est.noise
    assert isinstance(model, NoiseModel)
    params = est.params_mean()
    np.testing.assert_array_equal(est.sensor_cov_at(params, 0.4), model.sensor_cov_at(params, 0.4))
    assert est.sensor_cov_at(params, np.array([0.3, 0.4])).shape == (2, 6, 6)
    mean, cov = model.motion_noise("none", params, None, np.zeros((6, 10)), [], 0.4)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(cov, model.sensor_cov_at(params, 0.4))
    # The floors and the mismatch's model error are white-equivalent per update alike.
    c = decorrelation_updates(est.balance_filter.delay_s, est.update_every * est.dt_s)
    assert model.correlated == pytest.approx(c) and c > 1
    floors = np.array([2.5e-6, 6.6e-7])
    np.testing.assert_allclose(np.diag(model.floor_cov)[[0, 3]], c * floors**2)
    assert model.mismatch_model_var == pytest.approx(c * 5.3e-7**2)
    wrench = np.array([1.0, 0, 0, 0, 0, 0.1])
    pose = model.relative_pose_cov(wrench, 8)
    assert pose[0, 0] == pytest.approx(0.25 * model.loc_att_std**2)
    assert pose[5, 5] > pose[0, 0] > 0


def test_noise_model_rejects_bad_input():
    robot = _robot()
    kw = dict(force_std_n=1e-4, torque_std_nm=1e-5, actuation_noise=(0, 0, 0, 0))
    with pytest.raises(ValueError, match="sensor_noise"):
        NoiseModel(robot, 0.016, 10, 2, 0.25, 1.0, sensor_noise=(1e-3, -1, 0), **kw)
    with pytest.raises(ValueError, match="mismatch_model_std"):
        NoiseModel(
            robot, 0.016, 10, 2, 0.25, 1.0, sensor_noise=(0, 0, 0), mismatch_model_std=-1, **kw
        )
    model = NoiseModel(robot, 0.016, 10, 2, 0.25, 1.0, sensor_noise=(0, 0, 0), **kw)
    with pytest.raises(ValueError, match="fusion"):
        model.motion_noise("peers", np.ones(10), None, np.zeros((6, 10)), [])


def test_excitation_snr_counts_sigmas_of_the_filtered_motion():
    """An instant whose grasp accelerates at k sigma of its linear noise (no rotation) stands
    k sigma above it; a lever adds the angular noise to the linear one."""
    model = CargoEstimator(_robot(), 0, [], 0.016).noise
    regressor = np.zeros((6, 10))
    assert model.excitation_snr(regressor, 0.4) == 0.0
    regressor[:3, 0] = [7.0 * model.acc_noise, 0.0, 0.0]
    assert model.excitation_snr(regressor, 0.0) == pytest.approx(7.0)
    assert model.excitation_snr(regressor, 0.4) < 7.0


def _chain_noise(robot, readings, std, n_rep, n_updates, params, rng):
    """Monte Carlo of the estimator's momentum chain (``Preprocessor``'s rate and product
    filters with the momentum-form sample, then the slow balance filter) at constant readings
    ``readings`` (accel, gyro, q, thrust) plus white noise of std ``std`` (accel, gyro, encoder)
    per step: the balance's model-side noise n = d(links + Y pi - thrust) at the update instants
    after the chain's memory, (n_rep, n_updates, 6)."""
    from astrocargo.estimator.momentum import SIZE, balance_from_filtered
    from astrocargo.estimator.preprocess import Preprocessor

    def residual(state):
        b = balance_from_filtered(state[0], state[1])
        return b.links + b.regressor @ params - b.thrust

    warm = 400  # steps: ten times the chain's delay
    sizes = np.array([3, 3, robot.n_joints])
    scale = np.repeat(std, sizes)
    out = np.empty((n_rep, n_updates, 6))
    for rep in range(n_rep + 1):  # replica 0: noise-free, the reference
        # With the encoders' noise its square's mean in Q is subtracted, as the estimator does.
        pre = Preprocessor(robot, DT, PRE_HZ, encoder_std_rad=std[2] if rep else 0.0)
        slow = StateVariableFilter(SIZE, DT * EVERY, SLOW_HZ)
        clean = np.concatenate(readings[:3])
        for k in range(warm + n_updates * UPDATE + 1):
            noise = rng.normal(size=clean.size) * scale if rep else 0.0
            a, g, q = np.split(clean + noise, np.cumsum(sizes)[:2])
            pre.step(a, g, q, readings[3])
            if k % EVERY == 0:
                slow.step(pre.product_filter.state[0])
            if k > warm and (k - warm) % UPDATE == 0:
                r = residual(slow.state)
                if rep == 0:
                    reference = r  # stationary: the same at every instant
                else:
                    out[rep - 1, (k - warm) // UPDATE - 1] = r - reference
    return out


def test_momentum_chain_noise_matches_a_monte_carlo_of_the_chain():
    """The noise model's exact linear map of each white sensor noise through the momentum chain
    (``NoiseModel.momentum_jacobians``: the sample's Jacobian, the chain's kernels and their lag
    covariances) against the estimator's own filters fed with noisy readings of a robot that
    turns steadily (0.15 rad/s), accelerates and thrusts, arm bent: the covariance of the
    balance's noise at one update and between updates 1 and 3 apart (the slow filter's memory
    correlates them), source by source and all together, within the Monte Carlo's spread."""
    from astrocargo.estimator.motion import kernel_lag_covariances

    robot = _robot()
    nj = robot.n_joints
    rng = np.random.default_rng(3)
    w = np.array([0.05, -0.1, 0.1])
    acc = np.array([0.01, -0.005, 0.008])  # the IMU point's, base frame (imu_rot applied below)
    q = np.linspace(0.4, -0.6, nj)
    thrust = np.array([0.1, -0.05, 0.08, 2e-3, -1e-3, 3e-3])
    rot = np.asarray(robot.imu_rot)
    readings = (rot.T @ acc, rot.T @ w, q, thrust)
    params = np.array([5.0, 0.05, 0.9, -0.05, 0.1, 0.08, 0.12, 0.0, 0.01, 0.0])
    # The noise-free chain's steady state (rates constant): its pre-filter state is the motion.
    pre_state = np.zeros((3, 12 + nj))
    pre_state[0] = np.concatenate((w, acc, q, np.asarray(robot.thrust_to_base) @ thrust))
    from astrocargo.estimator.chain_modes import momentum_noise_modes, sample_jacobian
    from astrocargo.estimator.motion import chain_kernels

    jac = sample_jacobian(robot.arrays, np.asarray(robot.imu_pos, dtype=float), w, acc, q,
                          np.zeros(nj), pre_state[0, 6 + nj :])  # fmt: skip
    # Steady motion: the map does not drift (its rate's columns are zero).
    d_links, d_y = momentum_noise_modes(jac, np.zeros_like(jac), nj)
    cols = d_links + (d_y @ params).T  # (6, 24 + 8 nj)
    lag_cov = kernel_lag_covariances(chain_kernels(DT, 8.0, PRE_HZ, SLOW_HZ, EVERY), UPDATE, 3)
    channels = [(k, slice(4 * k, 4 * k + 2), slice(0, 2)) for k in range(6)]
    channels += [(6 + j, slice(24 + 8 * j, 28 + 8 * j), slice(2, 6)) for j in range(nj)]
    stds = {"gyro": (0, 2e-4, 0), "accelerometer": (1e-3, 0, 0), "encoders": (0, 0, 1e-3)}
    stds["all"] = (1e-3, 2e-4, 1e-3)
    for name, std in stds.items():
        var = np.array([std[1]] * 3 + [std[0]] * 3 + [std[2]] * nj) ** 2
        predicted = sum(
            var[c] * cols[:, cs] @ lag_cov[:, ks, ks] @ cols[:, cs].T for c, cs, ks in channels
        )  # (4, 6, 6): lags 0 to 3
        n = _chain_noise(robot, readings, np.array(std), 30, 80, params, rng)
        scale = np.linalg.norm(predicted[0])
        for lag in (0, 1, 3):
            a, b = n[:, : 80 - lag].reshape(-1, 6), n[:, lag:].reshape(-1, 6)
            empirical = 0.5 * (a.T @ b + b.T @ a) / a.shape[0]
            err = np.linalg.norm(empirical - 0.5 * (predicted[lag] + predicted[lag].T)) / scale
            assert err < 0.3, (name, lag, err)


def test_lag_weighted_covariance_is_exact_for_a_scalar_regressor():
    """For a scalar regressor a_i and noise correlated as C(L) between updates L apart, the
    least-squares estimate sum a_i z_i / sum a_i^2 has the variance
    sum_ij a_i a_j C(i - j) / (sum a_i^2)^2: the filter is consistent at the white covariance
    W = C(0) + 2 sum_L rho(L) C(L) with the regressor's autocorrelation rho as
    ``RegressorAutocorrelation`` accumulates it (a slow sinusoid with an offset: rho near 1),
    and W is far from both C(0) and the long-run sum for noise read out of a derivative."""
    from astrocargo.estimator.motion import RegressorAutocorrelation, lag_weighted_covariance

    n_lags, n = 6, 4000
    a = 1.0 + np.sin(2 * np.pi * np.arange(n) / 40.0)
    # Derivative-like noise: C(0) = 2, C(1) = -1 (a differenced white sequence), zero beyond.
    lag_cov = np.zeros((n_lags + 1, 1, 1))
    lag_cov[0], lag_cov[1] = 2.0, -1.0
    acf = RegressorAutocorrelation(n_lags)
    for i in range(n):
        regressor = np.zeros((6, 10))
        regressor[0, 0] = a[i]
        acf.add(i, regressor)
    rho = acf.rho()
    assert 0.9 < rho[1] < 1.0 and rho[0] == 1.0
    w = lag_weighted_covariance(lag_cov, rho)[0, 0]
    exact = (2.0 * a @ a - 2.0 * a[1:] @ a[:-1]) / (a @ a)
    # Exact up to the run's two ends (rho normalises each lag by its pairs' power): 5 %.
    assert w == pytest.approx(exact, rel=0.05)
    assert 0.0 < w < 0.1 * lag_cov[0, 0, 0]  # far below C(0), above the long-run sum (zero)


def _rho_reference(power, cross):
    """rho(L) in array form: over the columns with power at lag 0, the mean of cross / power
    over those with power at lag L; a lag none has power at takes the longest lag below it
    that has; ones without any column."""
    n = power.shape[0]
    rho = np.ones(n)
    columns = power[0] > 0
    if not columns.any():
        return rho
    power, cross = power[:, columns], cross[:, columns]
    ok = power > 0
    ratio = np.where(ok, cross / np.where(ok, power, 1.0), 0.0)
    counted = ok.sum(axis=1)
    mean = ratio.sum(axis=1) / np.maximum(counted, 1)
    last = np.maximum.accumulate(np.where(counted > 0, np.arange(n), 0))
    rho[1:] = mean[last][1:]
    return rho


def test_autocorrelation_and_lag_weighted_covariance_equal_their_array_forms():
    """``motion.autocorrelation_of`` (compiled loops) equals rho's array form bit for bit, with
    columns without power, lags without pairs and no column at all; ``lag_weighted_covariance``
    equals W = G(0) + sum_L rho(L) (G(L) + G(L)^T) symmetrised, and W of a sub-block of the
    channels is that sub-block of W (``NoiseModel._refresh_factors`` takes the held channels'
    own G(L))."""
    from astrocargo.estimator.motion import autocorrelation_of, lag_weighted_covariance

    rng = np.random.default_rng(7)
    for n_lags in (0, 1, 5, 40):
        power = np.abs(rng.standard_normal((n_lags + 1, 10)))
        power *= rng.random((n_lags + 1, 10)) < 0.7  # some columns and lags without pairs
        power[0, :3] = 0.0  # columns without power at lag 0 do not count
        if n_lags > 2:
            power[n_lags - 1 :] = 0.0  # the longest lags not seen yet
        cross = rng.standard_normal((n_lags + 1, 10))
        np.testing.assert_array_equal(
            autocorrelation_of(power, cross), _rho_reference(power, cross)
        )
    np.testing.assert_array_equal(autocorrelation_of(np.zeros((4, 10)), cross[:4]), np.ones(4))

    lag_cov = rng.standard_normal((9, 12, 12))
    rho = rng.standard_normal(9)
    w = lag_cov[0] + np.einsum("l,lab->ab", rho[1:], lag_cov[1:] + lag_cov[1:].transpose(0, 2, 1))
    np.testing.assert_allclose(lag_weighted_covariance(lag_cov, rho), 0.5 * (w + w.T), rtol=1e-13)
    held = np.array([0, 1, 6, 7])
    sub = np.ascontiguousarray(lag_cov[:, held][:, :, held])
    np.testing.assert_array_equal(
        lag_weighted_covariance(sub, rho), lag_weighted_covariance(lag_cov, rho)[np.ix_(held, held)]
    )


def test_rate_square_terms_join_the_motion_modes():
    """The encoders' squared rate noise (``momentum.rate_square_terms``) enters the motion's
    modes: their covariance is var sum_k w_k b_k b_k^T, b_k = Q_links + Q_Y pi of each term (the
    covariance ``CargoEstimator._rate_square_cov`` adds without motion fusion), and the IMU's and
    encoders' modes come first, as many as ``momentum_motion.var`` says."""
    from astrocargo.estimator.momentum import cargo_regressor_parts, rate_square_terms

    robot = _robot()
    nj = robot.n_joints
    est = CargoEstimator(robot, 0, [], DT, sensor_noise=(1e-3, 2e-4, 1e-3))
    model = est.noise
    q = np.linspace(0.3, -0.5, nj)
    pre_state = np.zeros((3, 12 + nj))
    pre_state[0, 6 : 6 + nj] = q
    pre_state[1, 6 : 6 + nj] = 0.05
    terms, weights = rate_square_terms(robot, q)
    variances = 3e-5 * weights
    regressor = np.random.default_rng(0).normal(size=(6, 10))
    d_links, d_y = model.momentum_jacobians(100, regressor, pre_state, (terms, variances))
    n_rate = terms.shape[0]
    assert d_links.shape[1] == model.momentum_motion.var.size == 24 + 8 * nj + n_rate
    params = np.array([5.0, 0.05, 0.9, -0.05, 0.1, 0.08, 0.12, 0.0, 0.01, 0.0])
    modes = d_links[:, -n_rate:] + (d_y[-n_rate:] @ params).T
    b = np.array([t[12:18] + cargo_regressor_parts(t)[1] @ params for t in terms])
    np.testing.assert_allclose(modes @ modes.T, (b.T * variances) @ b, rtol=1e-10, atol=1e-18)
    np.testing.assert_array_equal(model.momentum_motion.var[-n_rate:], 1.0)


def test_noise_modes_carry_each_channel_s_factor():
    """``momentum_noise_modes``: the modes are the kernels' columns times the block-diagonal
    factor of their channel kind (4 per IMU axis, 8 per joint)."""
    import scipy.linalg

    from astrocargo.estimator.chain_modes import momentum_noise_modes

    rng = np.random.default_rng(2)
    nj = 2
    jac, jac_rate = rng.normal(size=(2, 33, 6 + 2 * nj))
    held, point = rng.normal(size=(4, 4)), rng.normal(size=(8, 8))
    cols_links, cols_y = momentum_noise_modes(jac, jac_rate, nj)
    links, y = momentum_noise_modes(jac, jac_rate, nj, held, point)
    factor = scipy.linalg.block_diag(*([held] * 6 + [point] * nj))
    np.testing.assert_allclose(links, cols_links @ factor, atol=1e-12)
    np.testing.assert_allclose(y, np.einsum("kab,km->mab", cols_y, factor), atol=1e-12)


@pytest.mark.parametrize("window", [0, 24])
def test_message_modes_condition_the_team_exactly(window):
    """A peer's modes sent as the 9 of ``NoiseModel.message_modes`` (with ``over_time``: its 24
    IMU modes whole and 9 for the rest) give the receiver the same conditioned mean and
    covariance (``motion_noise``, "team") as all of them: the receiver sees them only through
    their links' and grasp acceleration's joint covariance. With ``over_time`` the team's IMU map
    (``over_time_noise``) is part of that covariance: what remains is positive semi-definite."""
    from types import SimpleNamespace

    from astrocargo.estimator.geometry import skew
    from astrocargo.estimator.motion import grasp_acc_map

    robot = _robot()
    model = CargoEstimator(
        robot, 0, [1], DT, sensor_noise=(1e-3, 2e-4, 1e-3), over_time_window=window
    ).noise
    n = model.momentum_motion.var.size
    rng = np.random.default_rng(4)
    own = (rng.normal(size=(6, n)), rng.normal(size=(n, 6, 10)))
    peer_links, peer_y = rng.normal(size=(6, n)), rng.normal(size=(n, 6, 10))
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    transform = np.zeros((6, 6))
    transform[:3, :3] = transform[3:, 3:] = rot
    transform[3:, :3] = skew(np.array([0.1, -0.9, 0.05])) @ rot
    grasp = grasp_acc_map(peer_y)
    full = SimpleNamespace(grasp_acc=rng.normal(0.0, 0.01, 3), motion_links_jac=peer_links,
                           motion_grasp_jac=grasp, motion_var=model.momentum_motion.var,
                           motion_band=model.momentum_motion.band)  # fmt: skip
    links9, grasp9, ones = model.message_modes(peer_links, peer_y)
    fields = {"motion_links_jac": links9, "motion_grasp_jac": grasp9}
    sent = SimpleNamespace(**{**vars(full), **fields, "motion_var": ones, "motion_band": ones})
    params = np.array([5.0, 0.05, 0.9, -0.05, 0.1, 0.08, 0.12, 0.0, 0.01, 0.0])
    regressor = rng.normal(size=(6, 10))
    args = ("team", params, own, regressor)
    kwargs = {"own": model.momentum_motion}
    mean_full, cov_full = model.motion_noise(*args, [(transform, full)], **kwargs)
    mean_sent, cov_sent = model.motion_noise(*args, [(transform, sent)], **kwargs)
    np.testing.assert_allclose(mean_sent, mean_full, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov_sent, cov_full, rtol=1e-9, atol=1e-12 * np.abs(cov_full).max())
    if window:
        assert links9.shape == (6, 33)
        _, cov_t, imu = model.over_time_noise(*args, [(transform, sent)])
        np.testing.assert_allclose(cov_t, cov_sent, rtol=1e-12)
        assert imu.shape == (6, 12, 4)
        imu_cov = np.einsum("icx,jcx->ij", imu, imu)
        assert np.linalg.eigvalsh(cov_t - imu_cov).min() > -1e-9 * np.abs(cov_t).max()
        # Alone ("own", no peers) the map is this robot's 24 IMU modes at their levels.
        from astrocargo.estimator.motion import balance_noise_map, noise_cov

        _, _, alone = model.over_time_noise("own", params, own, regressor, [])
        level = model.momentum_motion.var[:24]
        expected = noise_cov(balance_noise_map(*own, params)[:, :24], level)
        np.testing.assert_allclose(np.einsum("icx,jcx->ij", alone, alone), expected, rtol=1e-9)


def test_own_modes_are_the_conditioned_map_kept_from_motion_noise():
    """``bias_compensation.own_modes``: this robot's columns of N - K D at unit variance,
    K = S_nd S_dd^+ (``motion.conditioned_maps``), the same array whether kept from the instant's
    ``motion_noise`` or computed alone (a fresh model), and N's own columns under "own"."""
    from types import SimpleNamespace

    from astrocargo.estimator.bias_compensation import own_modes
    from astrocargo.estimator.geometry import skew

    robot = _robot()
    kept_model, fresh_model = (
        CargoEstimator(robot, 0, [1], DT, sensor_noise=(1e-3, 2e-4, 1e-3)).noise for _ in "ab"
    )
    n = kept_model.momentum_motion.var.size
    rng = np.random.default_rng(7)
    jac = (rng.normal(size=(6, n)), rng.normal(size=(n, 6, 10)))
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    transform = np.zeros((6, 6))
    transform[:3, :3] = transform[3:, 3:] = rot
    transform[3:, :3] = skew(np.array([0.1, -0.9, 0.05])) @ rot
    peer = SimpleNamespace(grasp_acc=rng.normal(0.0, 0.01, 3),
                           motion_links_jac=rng.normal(size=(6, 9)),
                           motion_grasp_jac=rng.normal(size=(3, 9)), motion_var=np.ones(9),
                           motion_band=np.ones(9))  # fmt: skip
    peers = [(transform, peer)]
    params = np.array([5.0, 0.05, 0.9, -0.05, 0.1, 0.08, 0.12, 0.0, 0.01, 0.0])
    regressor = rng.normal(size=(6, 10))
    args = (params, jac, regressor, peers)
    kept_model.motion_noise(
        "team", *args, own=kept_model.momentum_motion, params_cov=1e-4 * np.eye(10)
    )
    kept, _ = own_modes(kept_model, "team", *args, slope=False)
    alone, _ = own_modes(fresh_model, "team", *args, slope=False)
    np.testing.assert_array_equal(kept, alone)
    n_map, d_map, _, level = fresh_model._team(fresh_model.momentum_motion, *args)
    s_dd = (d_map * level) @ d_map.T + fresh_model.mismatch_model_var * np.eye(3)
    gain = (n_map * level) @ d_map.T @ np.linalg.pinv(s_dd)
    expected = (n_map - gain @ d_map)[:, :n] * np.sqrt(level[:n])
    assert np.abs(gain @ d_map).max() > 1e-3 * np.abs(n_map).max()  # the conditioning acts
    np.testing.assert_allclose(kept, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    unconditioned, _ = own_modes(kept_model, "own", *args, slope=False)
    np.testing.assert_allclose(unconditioned, n_map[:, :n] * np.sqrt(level[:n]), rtol=1e-12)
