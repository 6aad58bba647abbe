"""The accelerometer fused with localization, fed a lag late (estimator/fused_motion.py) and the
estimator's option ``motion_lag_s``."""

import numpy as np
import pytest
from test_estimator import simulate

from astrocargo.envs.world import World
from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.fused_motion import (
    FusedMotion,
    Reading,
    coloured_lag_covariances,
    flush_team,
    fused_error_ratio,
)
from astrocargo.estimator.geometry import quat_to_mat
from astrocargo.estimator.motion import HELD_EXTENDED, kernel_lag_covariances
from astrocargo.estimator.noise_model import momentum_chain_kernels
from astrocargo.estimator.smoother import FixedLagSmoother, lagged_error_psd_ratio

DT = 0.016


def test_smoothed_error_autocovariance_matches_its_spectrum():
    """Monte Carlo of ``FixedLagSmoother`` on noise alone (the truth at rest, so its output is
    its error): the error's autocovariance over lags 0..40 periods equals the inverse transform
    of dt sigma_a^2 ``lagged_error_psd_ratio`` (the spectrum the noise model carries), within
    the estimate's sampling error; the fixes take the low-frequency part off the variance and
    leave negative lag covariances (the error's spectrum vanishes at zero frequency)."""
    dt, lag, fix_every, accel_std, pos_std = 0.1, 60, 3, 1e-3, 2e-4
    rng = np.random.default_rng(0)
    smoother = FixedLagSmoother(dt, accel_std, pos_std, lag)
    n = 60_000
    out = []
    for k in range(n):
        fix = pos_std * rng.normal(size=3) if k % fix_every == 0 else None
        smoother.step(accel_std * rng.normal(size=3), fix)
        a = smoother.lagged_acceleration()
        if a is not None and k > 2000:
            out.append(a)
    err = np.array(out)
    lags = np.arange(41)
    measured = np.array([np.mean(err[: len(err) - m] * err[m:]) for m in lags])
    n_fft = 1 << 14
    freq = np.fft.rfftfreq(n_fft, dt)
    ratio = lagged_error_psd_ratio(np.maximum(freq, 1e-6), lag, dt, accel_std, pos_std, fix_every)
    model = np.fft.irfft(accel_std**2 * ratio, n_fft)[lags]
    # Sampling error of a lag product's mean over ~3 * 58 000 samples, correlated over ~20.
    tol = 5 * accel_std**2 * np.sqrt(20 / (3 * len(err)))
    assert model[0] < 0.97 * accel_std**2 and model[1:].sum() < -0.01 * accel_std**2
    assert np.all(np.abs(measured - model) < tol), np.c_[measured, model] / accel_std**2


def test_coloured_lag_covariances_white_equal_the_kernels():
    """With a white input the FFT's lag covariances are the direct sums
    (``motion.kernel_lag_covariances``); with the fused spectrum G(0) falls (the fixes remove
    low-frequency noise) and stays positive semi-definite."""
    kernels = momentum_chain_kernels(DT, 8.0, 1.0, 0.25, 2)[0][HELD_EXTENDED]
    white = coloured_lag_covariances(kernels, DT, 10, 30)
    np.testing.assert_allclose(white, kernel_lag_covariances(kernels, 10, 30), atol=1e-12)
    ratio = fused_error_ratio(500, DT, 1e-3, 5e-3, 20)
    fused = coloured_lag_covariances(kernels, DT, 10, 30, ratio)
    assert np.trace(fused[0]) < np.trace(white[0])
    assert np.linalg.eigvalsh(fused[0]).min() > -1e-12 * np.trace(fused[0])


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_fused_reading_is_the_smoother_turned_back_into_imu_axes():
    """A robot at rest, yawed 90 degrees, IMU rotated and off the base origin: the readings
    leave ``lag`` steps late, each accelerometer reading replaced by (R_WB R_BI)^T of the
    smoother's lagged output on the world-axes readings and the IMU point's fixes."""
    lag, fix_every, accel_std, pos_std = 25, 5, 1e-3, 5e-3
    imu_rot, imu_pos = _rot_z(0.3), np.array([0.1, -0.05, 0.02])
    quat = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 degrees about z
    rot_wi = quat_to_mat(quat) @ imu_rot
    fused = FusedMotion(DT, lag, accel_std, pos_std, 0.0, imu_rot, imu_pos)
    ref = FixedLagSmoother(DT, accel_std, pos_std, lag)
    rng = np.random.default_rng(1)
    base_pos, q, thrust = np.array([1.0, 2.0, 0.5]), np.zeros(2), np.zeros(6)
    fix_imu = base_pos + quat_to_mat(quat) @ imu_pos
    sent, expected = {}, {}
    for k in range(200):
        accel = accel_std * rng.normal(size=3)
        fix = k % fix_every == 0
        noise = pos_std * rng.normal(size=3) if fix else None
        reading = Reading(k, accel, np.zeros(3), q, thrust, base_pos + noise if fix else None,
                          quat if fix else None, None)  # fmt: skip
        sent[k] = accel
        ref.step(rot_wi @ accel, fix_imu + noise if fix else None)
        smoothed = ref.lagged_acceleration()
        if smoothed is not None:
            expected[k - lag] = rot_wi.T @ smoothed
        out = fused.push(reading)
        if k < lag:
            assert out is None
            continue
        assert out.stamp == k - lag
        want = expected.get(out.stamp, sent[out.stamp])
        np.testing.assert_allclose(out.accel, want, atol=1e-12)
    tail = fused.flush()
    assert [r.stamp for r in tail] == list(range(200 - lag, 200))
    assert not fused.buffer


def _two_robot_ideal(lag_s, seconds=20.0):
    return simulate(2, "ideal", seconds, "figure8_tumble",
                    estimator_kwargs={"record": True, "motion_lag_s": lag_s})  # fmt: skip


def test_lag_with_nothing_to_fuse_is_the_same_flight_late():
    """Ideal sensors (no accelerometer noise: nothing to fuse) and a 1 s lag: before the flush
    each robot's pipeline is 1 s behind (its stamp, its messages'); after ``flush_team`` both
    robots hold the same updates and estimates as without the lag, to the last bit, and they
    converge."""
    world, plain = _two_robot_ideal(0.0)
    _, late = _two_robot_ideal(1.0)
    last = int(20.0 / DT) - 1
    lag_steps = int(round(1.0 / DT))
    for est in late:
        assert est.stamp == last - lag_steps
        assert len(est._fused.buffer) == lag_steps
    assert flush_team(late) > 0
    for i, (a, b) in enumerate(zip(plain, late, strict=True)):
        assert b.stamp == last and not b._fused.buffer
        assert a.counters == b.counters
        np.testing.assert_array_equal(a.params_mean(), b.params_mean())
        truth = world.cargo_params_in_grasp_frame(i)
        assert abs(b.params_mean()[0] - truth[0]) < 2e-3 * truth[0]


def test_fused_flight_converges_and_flush_feeds_everything():
    """Two robots, nominal noise, 30 s with a 4 s lag: the accelerometer readings the pipeline
    takes differ from the raw ones, the flush feeds every buffered reading (the pipeline ends at
    the last stamp with nothing pending), and the estimate is within 4 of its standard
    deviations of the truth in every parameter."""
    kwargs = {"record": True, "motion_lag_s": 4.0}
    world, estimators = simulate(2, "nominal", 30.0, "figure8_tumble", estimator_kwargs=kwargs)
    flush_team(estimators)
    for i, est in enumerate(estimators):
        assert est.stamp == int(30.0 / DT) - 1
        assert est.counters["pending"] == 0 and est.counters["skipped_missing"] == 0
        assert est.counters["updates"] > 80
        truth = world.cargo_params_in_grasp_frame(i)
        z = (est.params_mean() - truth) / est.params_std()
        assert np.all(np.abs(z) < 4.0), z
    assert estimators[0].noise._accel_factor is not None


def test_lag_zero_is_the_estimator_as_it_was():
    """``motion_lag_s=0`` (the default) builds no fused motion, and a flight with it equals the
    default estimator's bit for bit."""
    _, plain = simulate(2, "nominal", 8.0, "figure8_tumble")
    _, zero = simulate(2, "nominal", 8.0, "figure8_tumble", estimator_kwargs={"motion_lag_s": 0})
    for a, b in zip(plain, zero, strict=True):
        assert b._fused is None and b.flush() == []
        np.testing.assert_array_equal(a.params_mean(), b.params_mean())
        np.testing.assert_array_equal(a.params_cov(), b.params_cov())


@pytest.mark.parametrize("lag", [-1.0, np.nan, np.inf, 0.001])
def test_bad_lag_raises(lag):
    robot = World(2).robot_model(0)
    with pytest.raises(ValueError, match="motion_lag_s"):
        CargoEstimator(robot, 0, [1], DT, motion_lag_s=lag)


def test_skipped_stamp_raises():
    """The smoother needs every control step: a gap in the stamps is an error."""
    est = CargoEstimator(World(2).robot_model(0), 0, [1], DT, motion_lag_s=0.5)
    args = (np.zeros(3), np.zeros(3), np.zeros(2), np.zeros(6))
    est.step(0, *args)
    with pytest.raises(ValueError, match="every control step"):
        est.step(2, *args)


def test_over_time_window_takes_the_fused_accelerometer_per_channel():
    """With a window and a lag the window's mode covariances are one per robot channel: the
    gyro's the raw chain's, the accelerometer's those of the fused spectrum (lower at lag 0)."""
    robot = World(2).robot_model(0)
    raw = CargoEstimator(robot, 0, [1], DT, over_time_window=8).noise.mode_lag_cov
    est = CargoEstimator(robot, 0, [1], DT, over_time_window=8, motion_lag_s=8.0)
    gm = est.noise.mode_lag_cov
    assert gm.shape == (raw.shape[0], 6, 4, 4)
    for c in range(3):
        np.testing.assert_array_equal(gm[:, c], raw)
        np.testing.assert_array_equal(gm[:, 3 + c], gm[:, 3])
    factor = est.noise._accel_factor
    held = est.noise._held_factor
    assert np.trace(factor @ factor.T) < np.trace(held @ held.T)


def test_missing_and_non_finite_readings_leave_unchanged_and_late():
    """A missing IMU frame and a NaN accelerometer reading leave the buffer as they came (the
    estimator holds and taints them), the smoother holding the last usable reading; the
    readings around them are still corrected (changed by the smoother, finite)."""
    lag = 10
    fused = FusedMotion(DT, lag, 1e-3, 5e-3, 0.0, np.eye(3), np.zeros(3))
    rng = np.random.default_rng(2)
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    raw, outs = {}, {}
    for k in range(120):
        accel, gyro = 1e-3 * rng.normal(size=3), np.zeros(3)
        if k == 60:
            accel, gyro = None, None
        if k == 70:
            accel = np.array([np.nan, 0.0, 0.0])
        raw[k] = accel
        fix = k % 5 == 0
        reading = Reading(k, accel, gyro, np.zeros(2), np.zeros(6),
                          np.zeros(3) if fix else None, quat if fix else None, None)  # fmt: skip
        out = fused.push(reading)
        if out is not None:
            outs[out.stamp] = out
    assert sorted(outs) == list(range(120 - lag))
    assert outs[60].accel is None and outs[60].gyro is None
    assert np.isnan(outs[70].accel[0])
    for k in (50, 65, 80):
        assert np.all(np.isfinite(outs[k].accel))
        assert not np.array_equal(outs[k].accel, raw[k])


def test_wrong_shapes_raise_at_once_with_a_lag():
    """With a lag a wrongly shaped reading raises when it comes, not a lag later."""
    est = CargoEstimator(World(2).robot_model(0), 0, [1], DT, motion_lag_s=0.5)
    args = [np.zeros(3), np.zeros(3), np.zeros(2), np.zeros(6)]
    est.step(0, *args)
    with pytest.raises(ValueError, match="thrust_command"):
        est.step(1, *args[:3], np.zeros(5))
    with pytest.raises(ValueError, match="base_pos_world"):
        est.step(1, *args, np.zeros(2), np.array([1.0, 0.0, 0.0, 0.0]))
