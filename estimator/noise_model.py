"""The measurement covariance of one robot's filtered wrench balance (``cargo_estimator``).

The balance of update k, thrust_k = links_k + Y_k pi - sum_j T_ij W_j,k, is built from filtered
signals (the pre-filter, then one slow filter over every balance term, sampled every
``update_every`` control steps). Its error has four independent parts, each carried to the
grasp frame G (moments about the grasp point) and summed:

    R_k = R_model + R_act,k / update_every + R_motion,k + R_peer,k,

- R_model, the floors: the balance's model error, what remains of the filtered balance with no
  noise in it (in the momentum form, the rate filter's departure from a pure delay under the
  products of the motion), as the variance of an independent residual per update:
  c diag(f^2 I, t^2 I), c the number of updates per decorrelation time of the slow filter
  (``decorrelation_updates``): its long-run variance, not weighted by the regressor's
  autocorrelation as the IMU's channels are (measured, that weighting leaves least squares on the
  noiseless flight 2.4-2.8 times overconfident: ``scripts/floors_consistency.py``);
- R_act: the actuation's white per-step noise (std abs + rel |command| per thruster axis, the
  robot's own, and the peers' sent with their messages), averaged over the update's window;
- R_motion: the sensors' white noise (gyro, accelerometer, encoders) carried through the momentum
  chain (``momentum_jacobians``): the rate filter, the momentum-form sample's exact Jacobian in
  the rate filter's value and derivative (products, rotations by the joint angles, the thrust
  turned into G), the product filter and the slow filter read out as value (thrust, Q) and
  derivative (P); and, with the team's motion fusion, conditioned on what the peers' IMUs report
  (``motion_noise``);
- R_peer: the channel's noise on the peers' wrenches and the error of a fix-averaged relative
  grasp pose (``relative_pose_cov``).

Correlated updates. The slow filter's memory (about 1 s) spans several updates (6.25 Hz), so the
sensor noise of successive updates is correlated, C(L) between updates L apart. The filter treats
updates as independent; for noise independent of the regressor it is consistent when each
carries W = C(0) + sum_L rho(L) (C(L) + C(L)^T), rho the regressor's own autocorrelation over
updates (``motion.lag_weighted_covariance``: exact for a scalar regressor): the long-run
covariance for noise on the filtered values (a slow regressor sees its spectral density at zero
frequency), and far less for noise read out of a derivative (the gyro through the momenta), whose
spectral density vanishes at zero frequency and is weighed at the regressor's own frequencies.
The IMU's channels carry W. The encoders' noise is the regressor's own (dY pi: the joint rates in
the grasp's velocity and angular velocity carry almost all of it), where that weighting fails:
the gain multiplies the regressor's noise by the noise itself (errors in variables), a bias of
relative size var(dY) / var(Y) that W, far below C(0) for noise read out of a derivative, leaves
uncovered (one robot, encoders alone: NEES 66 at W, 6 at C(0)). Their modes carry the per-update
covariance C(0); their correlation over updates is in the reported covariance
(``encoder_covariance``; ``CargoEstimator``'s default without a window, ``encoders_over_time``).
With ``over_time`` (``CargoEstimator(over_time_window=L)``, off by default) the IMU's channels
carry C(0) too, and the estimator weighs them over time instead (``over_time``,
``over_time_noise``). With the accelerometer fused with localization
(``CargoEstimator(motion_lag_s=...)``, ``fused_motion``) its noise is no longer white: its
channels' G(L) are those of the fused error's spectrum (``_init_fused_accelerometer``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .chain_modes import instant_noise_modes
from .copies import deepcopy_state
from .fused_motion import coloured_lag_covariances
from .instant_kernels import keep_motion, nearest_motion, record_constants, record_instant
from .momentum import SIZE, rate_square_terms
from .motion import (
    HELD_EXTENDED,
    POINT_EXTENDED,
    RegressorAutocorrelation,
    band_factors,
    chain_kernels,
    conditioned_noise,
    conditioned_own_modes,
    filtered_motion_gains,
    kernel_lag_covariances,
    lag_weighted_covariance,
    psd_factor,
    time_weighted_kernels,
)
from .over_time import IMU_MODES, MODES_PER_CHANNEL, conditioning_gain, mode_lag_covariances
from .preprocess import DEFAULT_RATE_CUTOFF_HZ, StateVariableFilter
from .records import as_interned
from .rne import RobotDescription
from .team_noise import (
    excitation_snr_kernel,
    message_factor,
    message_map,
    same_key,
    team_maps_of,
    team_noise,
)

# Ways the motion's sensor noise enters the measurement (``NoiseModel.motion_noise``).
MOTION_FUSION = ("none", "own", "team")
# Updates between refreshes of the IMU channels' lag-weighted factor (the regressor's
# autocorrelation changes slowly; ``NoiseModel.momentum_jacobians``).
FACTOR_REFRESH_UPDATES = 8
# ``momentum_jacobians`` without the squared rate noise's terms.
_NO_RATE_TERMS = (np.zeros((0, SIZE)), np.zeros(0))
_NO_RATE_AT = (np.zeros(0), 0.0)  # ``instant_modes`` without joint angles for them
_NO_COV = np.zeros((10, 10))  # ``_conditioned`` without the posterior's spread
# The unit variances (and bands) of a message's 9 modes (``message_modes``): one read-only
# array, shared by every message.
_UNIT_MODES = np.ones(9)
_UNIT_MODES.setflags(write=False)


def _team_key(own, params, motion_jac, regressor, peers) -> tuple:
    """What names one instant's team maps (``team_noise.same_key``): the parameters' bytes and
    the other inputs' objects."""
    inputs = (own, *motion_jac, regressor, *[x for pair in peers for x in pair])
    return np.asarray(params, dtype=float).tobytes(), inputs


class PeerMotion(Protocol):
    """What a peer sends about its filtered motion (the fields of ``WrenchMessage``)."""

    grasp_acc: np.ndarray | None  # (3,) filtered acceleration of its grasp point, its G axes
    motion_links_jac: np.ndarray | None  # (6, n) d links_G / d xi
    motion_grasp_jac: np.ndarray | None  # (3, n) d grasp_acc / d xi
    motion_var: np.ndarray | None  # (n,) per-sample variance of its filtered xi's noise
    motion_band: np.ndarray | None  # (n,) each coordinate's weight per update


def decorrelation_updates(slow_delay_s: float, update_s: float) -> float:
    """Updates per decorrelation time of the slow filter (at least 1): residuals of successive
    updates are correlated over 1 / (2 ENBW), ENBW = 3 w / 32 for (w / (s + w))^3 with
    w = 3 / delay; a slowly varying residual of rms s enters each update as c s^2."""
    w = 3.0 / slow_delay_s
    return max(1.0, (16.0 / (3.0 * w)) / update_s)


def _nonnegative(value, size: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{name} must be {size} finite non-negative numbers, got {value!r}")
    return arr


@functools.lru_cache(maxsize=16)
def momentum_chain_kernels(dt_s, rate_hz, product_hz, cutoff_hz, every):
    """The momentum chain's kernels with their time-weighted twins (12, span)
    (``motion.chain_kernels``, ``time_weighted_kernels`` about the Jacobians' instant) and the
    chain's delays (rate, product, slow filter; s). Cached, read-only."""
    kernels = chain_kernels(dt_s, rate_hz, product_hz, cutoff_hz, every)
    delays = [StateVariableFilter(1, dt_s, f).delay_s for f in (rate_hz, product_hz)]
    delays.append(StateVariableFilter(1, dt_s * every, cutoff_hz).delay_s)
    return time_weighted_kernels(kernels, dt_s, sum(delays)), tuple(delays)


@functools.lru_cache(maxsize=16)
def _momentum_chain(dt_s, rate_hz, product_hz, cutoff_hz, every, update_every):
    """What ``NoiseModel`` needs of the momentum chain, a pure function of its six numbers
    (cached: computed once per set-up, not per estimator and reset): the Jacobians' lag (control
    steps) and their drift's step (s), the kernels' lag covariances G (n_lags + 1, 12, 12) and
    the encoders' factor F (8, 8), F F^T = G(0) over their kernels (read-only arrays).

    The balance at an update sums the samples of about one chain delay before it: the Jacobians
    are taken there, from the pre-filter (which already lags by the product filter's delay) one
    slow-filter and one rate-filter delay back, with their rate."""
    kernels, delays = momentum_chain_kernels(dt_s, rate_hz, product_hz, cutoff_hz, every)
    n_lags = int(np.ceil(kernels.shape[1] / update_every))
    lag_cov = kernel_lag_covariances(kernels, update_every, n_lags)
    point = psd_factor(lag_cov[0][np.ix_(POINT_EXTENDED, POINT_EXTENDED)])
    for a in (lag_cov, point):
        a.setflags(write=False)
    return (delays[0] + delays[2]) / dt_s, delays[2], lag_cov, point


@dataclass(frozen=True)
class MotionNoiseSpec:
    """Per-coordinate variance of the motion's noise (``var``) and each coordinate's weight per
    update for its colour (``band``): for ``NoiseModel.motion`` the filtered xi = (a_B, wd_B,
    qdd) per sample and ``motion.band_factors``; for ``NoiseModel.momentum_motion`` each
    channel's per-sample variance (its modes carry the chain, band 1)."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    var: np.ndarray
    band: np.ndarray


class NoiseModel:
    """One robot's measurement covariance (see the module docstring).

    Args:
        robot: the robot's known model; ``dt_s`` the control period; ``update_every`` and
            ``regressor_every`` the control steps between updates and balance evaluations;
            ``cutoff_hz`` and ``kinematics_cutoff_hz`` the slow filter and the pre-filter.
        force_std_n, torque_std_nm: the balance's model error (R_model), rms per update of the
            filtered residual with no noise entering the balance.
        actuation_noise: (force_abs_n, force_rel, torque_abs_nm, torque_rel), white per control
            step: std = abs + rel * |command| per thruster axis.
        sensor_noise: (accel m/s^2, gyro rad/s, encoder rad), white per control step.
        peer_noise_std: (force N, moment N m) of the channel's noise on peers' wrenches.
        localization_noise: (position m, attitude rad) of one fix.
        mismatch_model_std: rms per update and axis (m/s^2) of the team mismatch's model error
            (what it holds with perfect sensors), weighted like the floors.
        over_time: the IMU's channels at their per-update covariance G(0) (not the lag-weighted
            W), their modes' covariance between updates in ``mode_lag_cov``
            (``over_time.mode_lag_covariances``) and ``message_modes`` sending them whole: for an
            estimator that conditions each update on the previous ones (``over_time``).
        accel_psd_ratio: None, the accelerometer white; f (Hz) -> r(f), its noise the fused
            acceleration's of ``fused_motion`` (PSD sigma_a^2 dt r(f)): its channels' kernels
            take that spectrum (``_init_fused_accelerometer``).

    The defaults' measured values (``CargoEstimator``; 90 s figure8_tumble, 2 robots, ``ideal``
    sensors, seed 0, the residual at the true parameters, momentum form): white-equivalent per
    update (Bartlett sum of the autocovariance over 32 updates, 3 decorrelation times) over the
    number of updates per decorrelation time, worst axis: 2.5e-6 N on the force rows, 6.6e-7 N m
    on the moment rows, 5.3e-7 m/s^2 on the mismatch. (The former acceleration form's were
    6.1e-5 N, 2.1e-5 N m and 1.7e-5 m/s^2.) ``motion`` is the acceleration form's model of the
    motion noise (xi = (a_B, wd_B, qdd) of the 1 Hz pre-filter, ``filtered_motion_gains``,
    ``band_factors``), which the excitation designer plans with; the estimator uses
    ``momentum_motion`` and ``momentum_jacobians``.
    """

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(
        self,
        robot: RobotDescription,
        dt_s: float,
        update_every: int,
        regressor_every: int,
        cutoff_hz: float,
        kinematics_cutoff_hz: float,
        *,
        force_std_n: float,
        torque_std_nm: float,
        actuation_noise,
        sensor_noise,
        peer_noise_std=(0.0, 0.0),
        localization_noise=(0.0, 0.0),
        mismatch_model_std: float = 0.0,
        rate_cutoff_hz: float = DEFAULT_RATE_CUTOFF_HZ,
        over_time: bool = False,
        accel_psd_ratio=None,
    ) -> None:
        if not (force_std_n > 0 and torque_std_nm > 0):
            raise ValueError("force_std_n and torque_std_nm must be positive")
        if not (np.isfinite(mismatch_model_std) and mismatch_model_std >= 0):
            raise ValueError(
                f"mismatch_model_std must be finite and >= 0, got {mismatch_model_std}"
            )
        self.update_every = int(update_every)
        slow = StateVariableFilter(1, dt_s * regressor_every, cutoff_hz)
        self.correlated = decorrelation_updates(slow.delay_s, update_every * dt_s)
        self.floor_cov = self.correlated * np.diag([force_std_n**2] * 3 + [torque_std_nm**2] * 3)
        self.actuation_noise = _nonnegative(actuation_noise, 4, "actuation_noise")
        self.actuation_abs = np.repeat(self.actuation_noise[[0, 2]], 3)
        self.actuation_rel = np.repeat(self.actuation_noise[[1, 3]], 3)
        sensor = _nonnegative(sensor_noise, 3, "sensor_noise")
        peer = _nonnegative(peer_noise_std, 2, "peer_noise_std")
        self.peer_noise_cov = np.diag(np.repeat(peer**2, 3))
        self.has_peer_noise = bool(np.any(peer > 0))  # else its covariance adds zeros
        loc = _nonnegative(localization_noise, 2, "localization_noise")
        self.loc_pos_std, self.loc_att_std = (float(x) for x in loc)
        self.mismatch_model_var = self.correlated * float(mismatch_model_std) ** 2
        self.over_time = bool(over_time)
        self._last_team = None  # (key, maps) of the last ``_team`` call
        self._last_modes = None  # (key, condition, own modes) of the last ``motion_noise``
        self.accel_psd_ratio = accel_psd_ratio
        self._init_scalar_model(robot, dt_s, cutoff_hz, sensor)
        self._init_acceleration_form(robot, dt_s, kinematics_cutoff_hz, cutoff_hz,
                                     regressor_every, sensor)  # fmt: skip
        self._init_momentum_chain(robot, dt_s, rate_cutoff_hz, kinematics_cutoff_hz, cutoff_hz,
                                  regressor_every, sensor)  # fmt: skip
        self.robot_mass = robot.total_mass
        self.robot_inertia = sum(
            float(np.linalg.eigvalsh(link.inertia_com)[-1]) for link in robot.links
        )

    def _init_scalar_model(self, robot, dt_s, cutoff_hz, sensor) -> None:
        """The scalar model (``sensor_cov_at``): white noise of std s per step through the slow
        filter becomes s * g on the filtered value and its derivatives (``noise_gains``)."""
        gains = StateVariableFilter(1, dt_s, cutoff_hz).noise_gains()
        self.acc_noise = sensor[0] * gains[0]
        self.ang_acc_noise = sensor[1] * gains[1]
        self.joint_acc_noise = sensor[2] * gains[2]
        # The grasp's angular accelerations carry the joints' (doubly differentiated encoders).
        self.grasp_ang_acc_noise = np.hypot(
            self.ang_acc_noise, np.sqrt(robot.n_joints) * self.joint_acc_noise
        )

    def _init_acceleration_form(self, robot, dt_s, product_hz, cutoff_hz, every, sensor) -> None:
        """``motion``: the acceleration form's exact filter chain per motion source (``motion``
        module), which the excitation designer plans with."""
        chain = filtered_motion_gains(dt_s, product_hz, cutoff_hz, every)
        factors = band_factors(chain, dt_s, product_hz, cutoff_hz, self.update_every)
        sizes = [3, 3, robot.n_joints]
        self.motion = MotionNoiseSpec(
            var=np.repeat((sensor * chain) ** 2, sizes), band=np.repeat(factors, sizes)
        )

    def _init_momentum_chain(self, robot, dt_s, rate_hz, product_hz, cutoff_hz, every, sensor):
        """The momentum chain's kernels and their lag covariances (``motion.chain_kernels``),
        the regressor's autocorrelation, the per-mode variances (``momentum_motion``) and what
        ``momentum_jacobians`` needs of the robot."""
        # ``momentum_chain_kernels``' arguments (the kernels of ``motion_fusion_limits``).
        self.chain_args = (dt_s, rate_hz, product_hz, cutoff_hz, every)
        chain = _momentum_chain(*self.chain_args, self.update_every)
        self._jacobian_lag_steps, self._jacobian_rate_step_s, self._lag_cov = chain[:3]
        n_lags = self._lag_cov.shape[0] - 1
        self.autocorrelation = RegressorAutocorrelation(n_lags)
        self._held_factor = None  # refreshed every FACTOR_REFRESH_UPDATES updates
        self._factors = None  # ``_channel_factors``
        # Over time (``over_time``): the IMU's channels at their per-update covariance G(0),
        # and their modes' covariance between updates L apart (``over_time.mode_lag_covariances``).
        held_lags = np.ascontiguousarray(self._lag_cov[:, HELD_EXTENDED][:, :, HELD_EXTENDED])
        self._held_lag_cov = held_lags  # the held channels' G(L) (``_refresh_factors``)
        self.mode_lag_cov = None
        if self.over_time:
            self._held_factor, self.mode_lag_cov = mode_lag_covariances(held_lags)
        self._init_fused_accelerometer(n_lags)
        # The encoders (the regressor's own noise): the per-update covariance G(0), see
        # ``momentum_jacobians``.
        self._point_factor = chain[3]
        nj = robot.n_joints
        # The squared rate noise's modes (``momentum.rate_square_terms``), with the encoders.
        self._n_rate_modes = (nj * (nj + 1)) // 2 if sensor[2] > 0 else 0
        var = np.repeat([sensor[1] ** 2, sensor[0] ** 2, sensor[2] ** 2, 1.0],
                        [12, 12, 8 * nj, self._n_rate_modes])  # fmt: skip
        self.momentum_motion = MotionNoiseSpec(var=var, band=np.ones(var.size))
        self._mode_std = np.sqrt(var)  # ``message_modes``' scale, once
        self._robot, self._robot_arrays = robot, robot.arrays
        self._imu_pos = np.ascontiguousarray(robot.imu_pos, dtype=float)
        self._n_joints = nj
        self._dt_s = dt_s
        # ``record_instant``'s constant arguments as one record (``record_constants``).
        self._record = record_constants(
            robot.arrays, self._imu_pos, self._point_factor, self._mode_std, nj,
            self._n_rate_modes, self._jacobian_rate_step_s, dt_s,
        )  # fmt: skip
        # The recorded pre-filter states (``_delayed_motion``): a ring of stamps (K,), states
        # (K, 3, 12 + nj) and its span [first slot, count], made at the first instant.
        self._motion_ring: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _init_fused_accelerometer(self, n_lags: int) -> None:
        """The accelerometer fused with localization (``accel_psd_ratio`` r(f), None: raw):
        its error is the white reading's times a PSD ratio r(f) (``fused_motion``), so its
        kernels' lag covariances are G_a(L) = IFFT[conj(K) K r] (``coloured_lag_covariances``)
        in place of the white G(L); the gyro keeps the white ones. Window 0: the accelerometer's
        modes carry the lag-weighted W_a of G_a (``momentum_jacobians``); over time: its
        per-update G_a(0) and its modes' Gm_a(L), so that ``mode_lag_cov`` becomes one Gm per
        robot channel (n_lags + 1, 6, 4, 4): gyro x, y, z, then accelerometer x, y, z."""
        self._accel_lag_cov = self._accel_factor = None
        if self.accel_psd_ratio is None:
            return
        kernels = momentum_chain_kernels(*self.chain_args)[0][HELD_EXTENDED]
        self._accel_lag_cov = coloured_lag_covariances(
            kernels, self.chain_args[0], self.update_every, n_lags, self.accel_psd_ratio
        )
        if self.over_time:
            self._accel_factor, accel_modes = mode_lag_covariances(self._accel_lag_cov)
            per_channel = [self.mode_lag_cov] * 3 + [accel_modes] * 3
            self.mode_lag_cov = np.ascontiguousarray(np.stack(per_channel, axis=1))
            self.mode_lag_cov.setflags(write=False)

    def _channel_factors(self) -> np.ndarray:
        """Each held channel's factor F (6, 4, 4), gyro x, y, z then accelerometer x, y, z: the
        held factor, or with the fused accelerometer its own for the accelerometer's
        (``_init_fused_accelerometer``); cached until a factor changes."""
        if self._factors is None:
            accel = self._held_factor if self._accel_factor is None else self._accel_factor
            self._factors = np.array([self._held_factor] * 3 + [accel] * 3, dtype=float)
        return self._factors

    def momentum_jacobians(
        self,
        stamp: int,
        regressor: np.ndarray,
        pre_state: np.ndarray,
        rate_terms: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The balance's sensor-noise modes at update ``stamp`` in the momentum chain:
        (d links - d thrust (6, n), d Y (n, 6, 10)), each mode of unit variance per unit
        per-sample variance of its channel (``momentum_motion.var``).

        Derivation. White noise e_c on channel c (gyro or accelerometer axis, base frame, held; an
        encoder, point) moves the rate filter's value by r * e_c and its derivative by r' * e_c
        (impulse responses), hence the momentum-form sample by J_x (r * e_c) (J =
        ``sample_jacobian`` at x the motion of the balance's samples, with its drift J' over the
        chain's memory), and the balance, read out of the slow filter's value (thrust, Q) and
        derivative (P), by n_i = sum_k c_k (K_k * e_c)_i over the chain's kernels K_k
        (``chain_kernels``, ``time_weighted_kernels``) with columns c_k
        (``momentum_noise_modes``). Successive updates are correlated over the slow filter's
        memory: Cov(n_i, n_i+L) = s_c^2 C G_c(L) C^T (``kernel_lag_covariances``). The modes are
        C F_c with F_c F_c^T = W_c: for the IMU's channels the lag-weighted
        W_c = G_c(0) + sum_L rho(L) (G_c(L) + G_c(L)^T) (``lag_weighted_covariance``), rho the
        regressor's autocorrelation over the run so far (``RegressorAutocorrelation``, updated
        here with ``regressor``; the factor refreshed every ``FACTOR_REFRESH_UPDATES`` updates);
        for the encoders G_c(0) (module docstring). ``pre_state`` (3, 12 + nj): the pre-filter's
        state over [gyro_B, the IMU point's acceleration_B, q, thrust_B]
        (``preprocess.Preprocessor``).

        ``rate_terms``: the encoders' squared rate noise at this instant, (terms (k, ``SIZE``),
        variances (k,) per update) of ``momentum.rate_square_terms`` (variance w_k v^2 of term
        k's white coefficient, v the rate noise's variance): k further modes of unit variance,
        sqrt(var_k) (Q_links, Q_Y) of each term, value read-outs flat in the excitation's band;
        None (or no encoder noise): zero columns, so that the count stays that of
        ``momentum_motion.var``, n = 24 + 8 nj + nj (nj + 1) / 2 with encoder noise."""
        index = stamp // self.update_every
        x = self._delayed_motion(stamp, pre_state)
        if not self.over_time:
            self.autocorrelation.add(index, regressor)
            if self._held_factor is None or index % FACTOR_REFRESH_UPDATES == 0:
                self._refresh_factors()
        none = rate_terms is None or not self._n_rate_modes
        terms, variances = _NO_RATE_TERMS if none else rate_terms
        return instant_noise_modes(
            self._robot_arrays, self._imu_pos, x, self._n_joints, self._jacobian_rate_step_s,
            self._channel_factors(), self._point_factor, terms, variances, self._n_rate_modes,
        )  # fmt: skip

    def _refresh_factors(self) -> None:
        """The IMU channels' lag-weighted factors at the regressor's autocorrelation so far
        (``momentum_jacobians``)."""
        rho = self.autocorrelation.rho()
        self._held_factor = psd_factor(lag_weighted_covariance(self._held_lag_cov, rho))
        if self._accel_lag_cov is not None:
            self._accel_factor = psd_factor(lag_weighted_covariance(self._accel_lag_cov, rho))
        self._factors = None

    def instant_modes(
        self,
        stamp: int,
        regressor: np.ndarray,
        pre_state: np.ndarray,
        rate_terms: tuple[np.ndarray, np.ndarray] | None = None,
        rate_at: tuple[np.ndarray, float] | None = None,
    ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``momentum_jacobians`` then ``message_modes`` of its modes: ((d links, d Y), (F's
        links rows, its grasp rows, ones)). The squared rate noise: ``rate_terms`` as
        ``momentum_jacobians`` takes them, or ``rate_at`` = (joint angles q (n_joints,) rad,
        scale v): ``momentum.rate_square_terms`` at q with variances v w_k, made here. Not over
        time, one compiled call (``instant_kernels.record_instant``; the factors' refresh,
        every ``FACTOR_REFRESH_UPDATES`` updates, before it)."""
        if self.over_time:
            if rate_at is not None:
                rate_terms = self._rate_terms_at(*rate_at)
            jac = self.momentum_jacobians(stamp, regressor, pre_state, rate_terms)
            return jac, self.message_modes(*jac)
        index = stamp // self.update_every
        regressor = np.ascontiguousarray(regressor, dtype=float)
        add = not (self._held_factor is None or index % FACTOR_REFRESH_UPDATES == 0)
        if not add:
            self.autocorrelation.add(index, regressor)
            self._refresh_factors()
        none = not self._n_rate_modes
        terms, variances = _NO_RATE_TERMS if none or rate_terms is None else rate_terms
        rate_q, rate_scale = _NO_RATE_AT if none or rate_at is None else rate_at
        target = stamp - self._jacobian_lag_steps
        auto = self.autocorrelation
        links, y, factor = record_instant(
            self._record, self._channel_factors(), terms, variances, rate_q,
            float(rate_scale), self._ring_with_room(pre_state), (auto._cross, auto._power,
            auto._ring, auto._ring_power, auto._ring_index), int(stamp), pre_state, target,
            target - 2 * self.update_every, index, regressor, add,
        )  # fmt: skip
        return (links, y), (factor[:6], factor[6:], _UNIT_MODES)

    def _rate_terms_at(self, q, scale: float) -> tuple[np.ndarray, np.ndarray] | None:
        """``instant_modes``' ``rate_at`` as ``rate_terms``: ``momentum.rate_square_terms`` at
        joint angles ``q`` and ``scale`` times their weights; None without such modes."""
        if not self._n_rate_modes:
            return None
        terms, weights = rate_square_terms(self._robot, q)
        return terms, scale * weights

    # A copy keeps the record; an unpickled one (another process) has a new dtype object, which
    # is interned again (numba's dispatch recognises a record's dtype by identity).
    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._record = as_interned(self._record)

    def message_modes(
        self, d_links: np.ndarray, d_y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a peer needs of this robot's modes (``momentum_jacobians``: d links (6, n),
        d Y (n, 6, 10)), in 9 modes of unit variance: the peer's conditioning (``motion_noise``)
        sees them only through the links' map L (6, n) and the grasp acceleration's map
        A = d Y[:, :3, 0]^T (3, n) (the force rows' mass column, ``motion.grasp_acc_map`` at the
        grasp point), so their joint covariance M diag(v) M^T, M = [L; A], is all it uses, and F
        (9, 9) with F F^T = M diag(v) M^T carries it exactly (v = ``momentum_motion.var``).
        Returns (F's links rows (6, 9), its grasp rows (3, 9), ones (9,): variances and bands,
        one read-only array shared by every message).
        With ``over_time``: the 24 IMU modes as they are (scaled to unit variance), then 9 that
        carry the rest's (6, 33), (3, 33), ones (33,): the receiver weighs the IMU's over time
        (``over_time_noise``)."""
        if not self.over_time:
            factor = message_factor(d_links, d_y, self._mode_std)
            return factor[:6], factor[6:], _UNIT_MODES
        stacked = message_map(d_links, d_y, self._mode_std)
        # Over time: the IMU's modes as they are (the receiver weighs them across updates),
        # the rest (encoders, squared rates: white across updates) in 9.
        rest = stacked[:, IMU_MODES:]
        modes = np.hstack((stacked[:, :IMU_MODES], psd_factor(rest @ rest.T)))
        return modes[:6], modes[6:], np.ones(modes.shape[1])

    def _delayed_motion(self, stamp: int, pre_state: np.ndarray) -> np.ndarray:
        """The pre-filter's (value, derivative, second derivative) (3, 12 + nj) about
        ``_jacobian_lag_steps`` before ``stamp``: the recorded state nearest that instant, moved
        the rest of the way along its derivatives (first order); ``pre_state`` kept, and the
        states older than 2 updates before that instant dropped (``instant_kernels``)."""
        target = stamp - self._jacobian_lag_steps
        ring = self._ring_with_room(pre_state)
        keep_motion(*ring, int(stamp), pre_state, target - 2 * self.update_every)
        return nearest_motion(*ring, target, self._dt_s)

    def _ring_with_room(self, pre_state: np.ndarray) -> tuple[np.ndarray, ...]:
        """``_motion_ring`` with room for one more state (made, or twice as long, when full)."""
        ring = self._motion_ring
        if ring is not None and ring[2][1] < ring[0].shape[0]:
            return ring
        size, count = (8, 0) if ring is None else (2 * ring[0].shape[0], int(ring[2][1]))
        stamps, states = np.zeros(size, np.int64), np.zeros((size, 3, pre_state.shape[1]))
        if ring is not None:  # the held states in order, from slot 0
            order = (ring[2][0] + np.arange(count)) % ring[0].shape[0]
            stamps[:count], states[:count] = ring[0][order], ring[1][order]
        self._motion_ring = (stamps, states, np.array([0, count], np.int64))
        return self._motion_ring

    def relative_pose_cov(self, wrench: np.ndarray, n_fixes: int) -> np.ndarray:
        """Covariance (6, 6) a peer's wrench (in G) gains from the error of a relative grasp pose
        averaged over ``n_fixes`` simultaneous fixes of both robots (position sqrt(2 / N) sigma_p,
        attitude sqrt(2 / N) sigma_theta): the force turns, the moment turns and moves."""
        shrink = 2.0 / max(n_fixes, 1)
        var_att = shrink * self.loc_att_std**2
        var_pos = shrink * self.loc_pos_std**2
        f2 = float(wrench[:3] @ wrench[:3])
        n2 = float(wrench[3:] @ wrench[3:])
        return np.diag([var_att * f2] * 3 + [var_att * n2 + var_pos * f2] * 3)

    def excitation_snr(self, regressor: np.ndarray, lever_m: float) -> float:
        """How far the filtered motion of an instant stands above its noise: the larger of
        |a_G| / sigma_lin and |wd| / sigma_ang, with the grasp's angular acceleration noise
        sigma_ang (gyro and joints) and sigma_lin = hypot(sigma_a, L sigma_ang) at the
        base-to-grasp lever L (m); a_G and wd from the filtered regressor (6, 10) (its force
        rows' h-columns are skew(wd) + skew(w)^2: wd is their antisymmetric part)."""
        return excitation_snr_kernel(
            regressor, float(self.acc_noise), float(self.grasp_ang_acc_noise), float(lever_m)
        )

    def sensor_cov_at(self, params: np.ndarray, lever_m: float | np.ndarray) -> np.ndarray:
        """Measurement covariance (..., 6, 6) from the sensors' noise on the filtered
        accelerations at the cargo ``params`` (10,) (grasp frame) and base-to-grasp lever(s)
        ``lever_m`` (...) m, scalar per block, magnitudes only: force M sigma_a + m_c L sigma_qdd,
        moment J sigma_wd + M L sigma_a + m_c |c| L sigma_qdd, with M the robot-plus-cargo mass,
        L the lever and J the inertia about the grasp. The model of ``motion_fusion="none"``
        (and of a peer that sends no motion)."""
        m_c, i_xx, i_yy, i_zz = (float(x) for x in params[[0, 4, 5, 6]])
        com = float(np.linalg.norm(params[1:4])) / m_c
        lever = np.asarray(lever_m, dtype=float)
        total = self.robot_mass + m_c
        inertia = self.robot_inertia + self.robot_mass * lever**2 + max(i_xx, i_yy, i_zz)
        force = (total * self.acc_noise) ** 2 + (m_c * lever * self.joint_acc_noise) ** 2
        moment = (
            (inertia * self.ang_acc_noise) ** 2
            + (total * lever * self.acc_noise) ** 2
            + (m_c * com * lever * self.joint_acc_noise) ** 2
        )
        cov = np.zeros(lever.shape + (6, 6))
        axes = np.arange(3)
        cov[..., axes, axes] = force[..., None]
        cov[..., axes + 3, axes + 3] = moment[..., None]
        return self.correlated * cov

    def motion_noise(
        self,
        fusion: str,
        params: np.ndarray,
        motion_jac: tuple[np.ndarray, np.ndarray] | None,
        regressor: np.ndarray,
        peers: list[tuple[np.ndarray, PeerMotion]],
        lever_m: float = 0.0,
        own: MotionNoiseSpec | None = None,
        params_cov: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mean (6,) and covariance (6, 6) of the balance's motion noise at one recorded instant.

        ``fusion`` one of ``MOTION_FUSION``; ``params`` the cargo's parameters (10,) in G;
        ``motion_jac`` the instant's (d links (6, n), d Y (n, 6, 10)) (``rne``); ``regressor``
        its filtered Y (6, 10); ``peers`` per peer (T_ij (6, 6) wrench transform G_j -> G_i, its
        message); ``lever_m`` the base-to-grasp lever of the scalar model; ``own`` the variances
        of this robot's coordinates: ``momentum_motion`` for the modes of
        ``momentum_jacobians`` (the estimator's), None for ``motion`` (the acceleration form's
        xi of ``rne.balance_motion_jacobians``, the excitation designer's planning model);
        ``params_cov`` (10, 10) the uncertainty of ``params``: the regressor's noise moves the
        balance by dY pi with the true pi, so over the posterior its covariance is
        dY (pi pi^T + P) dY^T, the dY P dY^T part uncorrelated with the mismatch and added after
        the conditioning (None: P = 0).

        "none" (or a peer that sends no motion): zero mean, ``sensor_cov_at``. "own": E Sigma E^T
        over this robot and the peers (``motion.condition_on_mismatch`` without a mismatch).
        "team": that, conditioned on the peers' grasp-acceleration mismatches
        d_j = R_ij a_Gj - (a_Gi + (skew(wd) + skew(w)^2) r_ij), zero in truth for a rigid cargo:
        E[n | d] and Cov[n | d]."""
        if fusion not in MOTION_FUSION:
            raise ValueError(f"fusion must be one of {MOTION_FUSION}, got {fusion!r}")
        if (
            fusion == "none"
            or motion_jac is None
            or any(m.motion_links_jac is None for _, m in peers)
        ):
            return np.zeros(6), self.sensor_cov_at(params, lever_m)
        own = self.motion if own is None else own
        condition = fusion == "team" and bool(peers)
        key = _team_key(own, params, motion_jac, regressor, peers)
        mean, cov, modes = team_noise(
            own, params, motion_jac, regressor, peers, condition, self.mismatch_model_var,
            params_cov,
        )  # fmt: skip
        self._last_modes = (key, condition, modes)
        return mean, cov

    def _conditioned(self, condition, team, motion_jac, params_cov):
        """Mean and covariance of the motion noise from ``_team``'s maps, conditioned on the
        mismatch or not, with the posterior's spread (``motion_noise``)."""
        n_map, d_map, mismatch, level = team
        spread = params_cov is not None
        return conditioned_noise(
            n_map, d_map, mismatch, level, condition, self.mismatch_model_var,
            np.ascontiguousarray(motion_jac[1], dtype=float),
            np.ascontiguousarray(params_cov, dtype=float) if spread else _NO_COV, spread,
        )[:2]  # fmt: skip

    def own_modes(self, own, params, motion_jac, regressor, peers, condition) -> np.ndarray:
        """This robot's modes as the residual sees them, (N - K D)[:, :n] diag(level[:n])^1/2
        (6, n) from ``_team``'s maps (K D zero without ``condition``;
        ``motion.conditioned_own_modes``): the last ``motion_noise`` call's for the same
        instant (its arguments, as in ``_team``)."""
        last = self._last_modes
        key = _team_key(own, params, motion_jac, regressor, peers)
        if last is not None and last[1] == condition and same_key(last[0], key):
            return last[2]
        n_map, d_map, _, level = self._team(own, params, motion_jac, regressor, peers)
        var = self.mismatch_model_var
        return conditioned_own_modes(n_map, d_map, level, condition, var, own.var.size)

    def over_time_noise(
        self,
        fusion: str,
        params: np.ndarray,
        motion_jac: tuple[np.ndarray, np.ndarray] | None,
        regressor: np.ndarray,
        peers: list[tuple[np.ndarray, PeerMotion]],
        lever_m: float = 0.0,
        params_cov: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``motion_noise`` of the estimator's modes (``momentum_motion``; ``over_time`` on) and
        the conditioned map of the team's IMU modes, J = (N - K D)[:, imu] diag(level)^1/2
        (6, c, 4), c = 6 channels per robot (this robot's, then the peers' in order; K the
        mismatch's gain, zero for "own"): their part of the covariance is J J^T and, between
        updates, ``over_time.UpdateWindow``'s J_k Gm J_l^T. J None where a peer sends no IMU
        modes (its message is not ``over_time``'s) or without motion fusion."""
        own = self.momentum_motion
        sizes = [
            np.shape(m.motion_links_jac)[1] for _, m in peers if m.motion_links_jac is not None
        ]
        if fusion == "none" or motion_jac is None or sizes != [IMU_MODES + 9] * len(peers):
            mean, cov = self.motion_noise(
                fusion, params, motion_jac, regressor, peers, lever_m, own, params_cov
            )
            return mean, cov, None
        team = self._team(own, params, motion_jac, regressor, peers)
        condition = fusion == "team" and bool(peers)
        mean, cov = self._conditioned(condition, team, motion_jac, params_cov)
        n_map, d_map, _, level = team
        if condition:
            n_map = n_map - conditioning_gain(n_map, d_map, level, self.mismatch_model_var) @ d_map
        n_own = self.momentum_motion.var.size
        starts = [0] + [n_own + k * (IMU_MODES + 9) for k in range(len(peers))]
        cols = np.concatenate([np.arange(s, s + IMU_MODES) for s in starts])
        imu = n_map[:, cols] * np.sqrt(level[cols])
        return mean, cov, imu.reshape(6, -1, MODES_PER_CHANNEL)

    def _team(self, own, params, motion_jac, regressor, peers):
        """The team's noise map N, mismatch map D, mismatch d (``team_noise.team_maps``) and the
        per-mode levels var * band. The last call's maps are kept (read-only) and returned
        again for the same instant (the same arrays and messages, ``params`` equal):
        ``over_time_noise`` and ``bias_compensation.own_modes`` (its slope) ask for the same
        maps. (``motion_noise`` builds them inside its one compiled call.)"""
        key = _team_key(own, params, motion_jac, regressor, peers)
        last = self._last_team
        if last is not None and same_key(last[0], key):
            return last[1]
        team = team_maps_of(own, params, motion_jac, regressor, peers)
        for array in team:
            array.flags.writeable = False
        self._last_team = (key, team)
        return team
