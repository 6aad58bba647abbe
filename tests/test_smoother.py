"""The fixed-lag smoother of a base's acceleration (``estimator.smoother``): against filterpy's
Kalman filter and RTS smoother, and its error spectrum against the closed-form Wiener one."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from astrocargo.estimator.smoother import (
    FixedLagSmoother,
    crossover_hz,
    fused_psd_ratio,
    lagged_error_psd_ratio,
    smooth_record,
)

DT = 1 / 62.5
ACCEL_STD = 1e-3
POS_STD = 5e-3
FIX_EVERY = 20  # nominal: 3.125 Hz


def _record(n: int, seed: int, signal: bool = True):
    """Readings and fixes of a base flying a smooth path (or resting, ``signal`` False)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    w = np.array([0.11, 0.22, 0.39])
    acc = 0.01 * np.sin(np.outer(t, w)) if signal else np.zeros((n, 3))
    vel = np.cumsum(acc, axis=0) * DT
    pos = np.cumsum(vel, axis=0) * DT
    u = acc + ACCEL_STD * rng.standard_normal((n, 3))
    has_fix = np.arange(n) % FIX_EVERY == 0
    fixes = pos + POS_STD * rng.standard_normal((n, 3))
    return u, fixes, has_fix, acc


def test_matches_filterpy_rts():
    """filterpy's ``rts_smoother`` ignores the control input, so the reference runs on the state
    less its response to the readings (x^u_k = F x^u_k-1 + B u_k, x^u_0 = 0): x - x^u has no
    input, and the fixes of it are y_k - p^u_k."""
    u, fixes, has_fix, _ = _record(600, 0)
    states, acc = smooth_record(u, fixes, has_fix, DT, ACCEL_STD, POS_STD)
    f = np.array([[1.0, DT], [0.0, 1.0]])
    b = np.array([[0.5 * DT**2], [DT]])
    driven = np.zeros((len(u), 2, 3))
    for k in range(1, len(u)):
        driven[k] = f @ driven[k - 1] + b @ u[k][None]
    for axis in range(3):
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.F, kf.Q = f, ACCEL_STD**2 * b @ b.T
        kf.H, kf.R = np.array([[1.0, 0.0]]), np.array([[POS_STD**2]])
        kf.x = np.array([[fixes[0, axis]], [0.0]])
        kf.P = np.diag([POS_STD**2, 1.0])
        xs, ps = [kf.x.copy()], [kf.P.copy()]
        for k in range(1, len(u)):
            kf.predict()
            if has_fix[k]:
                kf.update(np.array([[fixes[k, axis] - driven[k, 0, axis]]]))
            xs.append(kf.x.copy())
            ps.append(kf.P.copy())
        ref = kf.rts_smoother(np.array(xs), np.array(ps))[0][:, :, 0] + driven[:, :, axis]
        np.testing.assert_allclose(states[:, :, axis], ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(acc[:, axis], np.diff(ref[:, 1]) / DT, atol=1e-9)


def test_fixed_lag_is_the_window_smoother_and_converges():
    """Its output lag periods back is the record's smoother on the data seen so far; with a lag
    of several 1 / (2 pi f_x) it is the whole record's smoother."""
    n, lag = 2400, 1000
    u, fixes, has_fix, _ = _record(n, 1)
    smoother = FixedLagSmoother(DT, ACCEL_STD, POS_STD, lag)
    out = []
    for k in range(n):
        smoother.step(u[k], fixes[k] if has_fix[k] else None)
        out.append(smoother.lagged_acceleration())
    assert all(x is None for x in out[: lag + 1]) and out[lag + 1] is not None
    k = 2200
    _, acc_seen = smooth_record(
        u[: k + 1], fixes[: k + 1], has_fix[: k + 1], DT, ACCEL_STD, POS_STD
    )
    np.testing.assert_allclose(out[k], acc_seen[k - lag - 1], rtol=1e-7, atol=1e-12)
    _, acc_all = smooth_record(u, fixes, has_fix, DT, ACCEL_STD, POS_STD)
    lagged = np.array(out[lag + 1 :])
    m = len(lagged)
    # What the fixes correct (the smoothed less the read acceleration), lagged against whole:
    # measured 0.97 of it at a lag of 100 periods, 0.39 at 600, 0.07 at 1000 (5 / (2 pi f_x)).
    correction = acc_all[:m] - u[1 : m + 1]
    gap = lagged - acc_all[:m]
    assert np.sqrt(np.mean(gap**2)) < 0.15 * np.sqrt(np.mean(correction**2))


def test_error_spectrum_is_the_wiener_one():
    """Error periodogram below and around the crossover over S_fused: 1 on average; over the
    accelerometer's own PSD well below 1 (what the fixes add)."""
    n = int(3000 / DT)
    u, fixes, has_fix, acc = _record(n, 2, signal=False)
    _, est = smooth_record(u, fixes, has_fix, DT, ACCEL_STD, POS_STD)
    err = (est - acc[1:])[n // 10 : -n // 10]
    f_x = crossover_hz(ACCEL_STD, DT, POS_STD, FIX_EVERY * DT)
    assert f_x == pytest.approx(0.0337, abs=2e-4)
    freq = np.fft.rfftfreq(err.shape[0], DT)
    power = np.abs(np.fft.rfft(err, axis=0)) ** 2 * DT / err.shape[0]  # two-sided PSD estimate
    band = (freq > 0.3 * f_x) & (freq < 3 * f_x)
    s_a = ACCEL_STD**2 * DT
    fused = s_a * fused_psd_ratio(freq[band], f_x)
    assert np.mean(power[band] / fused[:, None]) == pytest.approx(1.0, abs=0.1)
    below = (freq > 0.3 * f_x) & (freq < f_x)
    assert np.mean(power[below]) / s_a < 0.4
    above = (freq > 10 * f_x) & (freq < 1.0)
    assert np.mean(power[above]) / s_a == pytest.approx(1.0, abs=0.05)


def test_rejects_bad_input():
    with pytest.raises(ValueError, match="lag_steps"):
        FixedLagSmoother(DT, ACCEL_STD, POS_STD, 0)
    with pytest.raises(ValueError, match="must be > 0"):
        FixedLagSmoother(DT, -1.0, POS_STD, 10)
    with pytest.raises(ValueError, match="finite"):
        FixedLagSmoother(DT, ACCEL_STD, POS_STD, 10).step(np.array([np.nan, 0, 0]), None)
    resting = FixedLagSmoother(DT, ACCEL_STD, POS_STD, 10)
    for _ in range(30):  # no fix yet: nothing starts
        resting.step(np.zeros(3), None)
    assert resting.periods == 0 and resting.lagged_acceleration() is None
    u, fixes, has_fix, _ = _record(50, 3)
    has_fix[0] = False
    with pytest.raises(ValueError, match="first period"):
        smooth_record(u, fixes, has_fix, DT, ACCEL_STD, POS_STD)
    with pytest.raises(ValueError, match="must be > 0"):
        crossover_hz(ACCEL_STD, DT, 0.0, 0.32)


@pytest.fixture(scope="module")
def limits():
    """scripts/motion_fusion_limits.py as a module (``test_scripts.load``)."""
    from test_scripts import load

    return load("motion_fusion_limits")


def _synthetic_recording(k: int, seed: int) -> dict:
    """A recording like ``motion_fusion_limits.fly``'s without a flight: random regressors,
    covariances and team IMU maps J (6, 12 channels, 4) of two robots, one update apart."""
    rng = np.random.default_rng(seed)
    root = rng.standard_normal((k, 6, 6))
    jac = 0.5 * rng.standard_normal((k, 6, 12, 4))
    motion = np.einsum("kicx,kjcx->kij", jac, jac)
    rec = {
        "A": rng.standard_normal((k, 6, 10)),
        "z": rng.standard_normal((k, 6)),
        "b": np.zeros((k, 6)),
        "R": root @ root.transpose(0, 2, 1) + np.eye(6) + motion,
        "J": jac,
        "index": np.arange(k),
        "truth": np.array([5.0, 0.1, -0.15, 0.2, 0.3, 0.4, 0.45, 0.01, 0.0, -0.01]),
    }
    rec.update(raw_z=rec["z"], raw_A=rec["A"], raw_b=rec["b"], raw_R=rec["R"])
    return rec


def test_run_covariance_without_lags_is_the_recorded_bound(limits):
    """With the modes uncorrelated between updates (Gm of lag 0 only) the whole-run covariance
    is the updates' own, block-diagonal: the benchmark's bound; correlated over one update it
    differs (it can fail)."""
    rec = _synthetic_recording(40, 4)
    white = np.eye(4)[None]

    def bound(cov):
        rows, _ = limits.whitened(limits.raw(rec), cov)
        return limits.principal_bound(rows, rec["truth"])

    expected = bound(rec["R"])
    np.testing.assert_allclose(bound(limits.run_covariance(rec, white, white)), expected,
                               rtol=1e-8)  # fmt: skip
    lagged = np.stack((np.eye(4), 0.8 * np.eye(4)))
    assert not np.allclose(bound(limits.run_covariance(rec, lagged, lagged)), expected, rtol=1e-2)


def test_mode_lags_are_the_noise_models(limits):
    """The script's modes' lag covariances through the kernels' FFT are the estimator's
    (``NoiseModel.mode_lag_cov``) for a white input (its own check against the kernels' direct
    sums passes); fused with localization the accelerometer's per-update variance falls."""
    model = limits.chain_model(2)
    np.testing.assert_allclose(limits.mode_lags(model), model.mode_lag_cov, atol=1e-9)
    fused = limits.mode_lags(model, lambda f: limits.fused_psd_ratio(f, 0.034))
    assert np.trace(fused[0]) < 0.999 * np.trace(model.mode_lag_cov[0])


def test_gls_nees_is_chi_square_when_the_covariance_is_the_noises(limits):
    """Mean NEES over draws ~10 (10 parameters) with the true covariance, ~40 when the noise is
    twice what the covariance says."""
    rec = _synthetic_recording(30, 5)
    rng = np.random.default_rng(6)
    chol = np.linalg.cholesky(rec["R"])
    rows, _ = limits.whitened(rec, rec["R"])
    for scale, expected in ((1.0, 10.0), (2.0, 40.0)):
        nees = []
        for _ in range(300):
            noise = scale * (chol @ rng.standard_normal((30, 6, 1)))[..., 0]
            z = np.einsum("kij,j->ki", rec["A"], rec["truth"]) + noise
            _, resid = limits.whitened({**rec, "z": z}, rec["R"])
            nees.append(limits.gls_nees(rows, resid, rec["truth"]))
        assert np.mean(nees) == pytest.approx(expected, rel=0.15)


def test_lagged_error_spectrum_tends_to_wiener_with_the_lag():
    """The fixed-lag smoother's error PSD (``lagged_error_psd_ratio``) at a lag of 5 / (2 pi f_x)
    is the Wiener one (measured at the nominal 62.5 Hz: within 0.004 at a 16 s lag); with a 1 s
    lag the fixes add almost nothing. Coarser periods with the same accelerometer PSD and fix
    period keep the test short."""
    dt, every = 4 * DT, FIX_EVERY // 4
    accel_std = ACCEL_STD / 2  # sigma^2 dt as at 62.5 Hz
    f_x = crossover_hz(accel_std, dt, POS_STD, every * dt)
    freq = np.array([0.3, 0.6, 1.0, 1.5, 3.0]) * f_x
    long = lagged_error_psd_ratio(freq, int(16 / dt), dt, accel_std, POS_STD, every, 300)
    np.testing.assert_allclose(long, fused_psd_ratio(freq, f_x), atol=0.02)
    short = lagged_error_psd_ratio(freq, int(1 / dt), dt, accel_std, POS_STD, every, 300)
    assert np.all(short[:3] > 0.8)
