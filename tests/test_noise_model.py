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
    floors = np.array([6.1e-5, 2.1e-5])
    np.testing.assert_allclose(np.diag(model.floor_cov)[[0, 3]], c * floors**2)
    assert model.mismatch_model_var == pytest.approx(c * 1.7e-5**2)
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
