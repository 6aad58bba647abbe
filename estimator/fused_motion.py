"""The robot's accelerometer fused with its localization fixes, fed to the estimator a lag late.

``CargoEstimator(motion_lag_s=lag)`` (0: off, the default) passes every control step's readings
through ``FusedMotion`` before its own pipeline (``per_step.EstimatorInputs.step``):

1. the readings of stamp t go into a ring buffer;
2. a fixed-lag smoother (``smoother.FixedLagSmoother``) of the IMU point's world acceleration
   runs forward on them: the accelerometer's period mean turned into world axes with this
   robot's own attitude at mid-period, u_W = R_WB(t - dt/2) R_BI a_I (R_WB from the fixes,
   propagated with the gyro between them, ``step_parts.update_attitude``), and the fix of the IMU
   point p_WI = p_WB + R_WB p_BI (the IMU's lever taken in the fix itself, so nothing about the
   angular motion enters; its attitude error adds |p_BI| sigma_theta per axis, 0.5 mm against
   5 mm at ``nominal``, to the fix's variance);
3. the readings of stamp t - lag leave the buffer with the accelerometer replaced by the
   smoothed one, a_I' = a_I + (R_WB R_BI)^T (a_W|N - u_W) (the smoother's correction turned
   back with the same rotation, so the rotation's own error cancels), and enter the estimator's
   pipeline as they are otherwise: balance, messages (with stamp t - lag), peers' updates.

So the estimate is ``lag`` behind: the observations' estimate at time t holds the data up to
t - lag. Every robot of a team must run the same lag (their messages' stamps are the
delayed ones). ``flush`` (at the end of a flight) feeds the buffered readings with the
smoothed accelerations of the smoother's whole window (fixed-interval smoothing of the tail),
so that a flight's estimate holds all its data.

Missing or non-finite accelerometer readings: the smoother holds the last usable reading and
those readings leave the buffer unchanged (the estimator holds and taints them as it does
without the lag). Readings before the first fix, and with no accelerometer noise (nothing to
fuse), leave unchanged.

The fused acceleration's error is not white: its PSD is S_a r(f), r the smoother's error ratio
(``smoother.lagged_error_psd_ratio``: 1 above the crossover with localization, falling as f^4
below it). ``coloured_lag_covariances`` carries it through the estimator's chain kernels (the
noise model's accelerometer channels, ``noise_model``).
"""

from __future__ import annotations

import functools
import itertools
from collections import deque
from typing import NamedTuple

import numpy as np

from .geometry import exp_so3
from .smoother import FixedLagSmoother, lagged_error_psd_ratio
from .step_parts import FIX, update_attitude

# Frequencies (Hz) at which the smoother's error ratio is tabulated (interpolated in log f
# between them; 1 above the last, where it is 1 within 1e-3 at any lag).
_RATIO_GRID_HZ = np.geomspace(1e-4, 2.0, 120)
# The least FFT length of ``coloured_lag_covariances`` (control steps: 17 min at 62.5 Hz).
_MIN_FFT = 1 << 16


class Reading(NamedTuple):
    """One control step's readings as ``CargoEstimator.step`` takes them."""

    stamp: int
    accel: np.ndarray | None
    gyro: np.ndarray | None
    q: np.ndarray
    thrust: np.ndarray
    pos: np.ndarray | None
    quat: np.ndarray | None
    servo_rate: np.ndarray | None


class _Buffered(NamedTuple):
    """A reading waiting for its smoothed acceleration, with its world rotation R_WI (3, 3)
    and its world-axes accelerometer reading u_W (3,) (None: nothing to correct)."""

    reading: Reading
    rot_world_imu: np.ndarray | None
    u_world: np.ndarray | None


def _finite(x) -> bool:
    return x is not None and np.shape(x) == (3,) and bool(np.all(np.isfinite(x)))


class FusedMotion:
    """Ring buffer, attitude and fixed-lag smoother of one robot (module docstring).
    ``lag_steps`` >= 1 control steps of ``dt_s``; ``accel_std`` m/s^2 per sample,
    ``position_std_m`` and ``attitude_std_rad`` of one fix; ``imu_rot`` R_BI, ``imu_pos`` p_BI
    (m) of the IMU in the base frame."""

    def __init__(self, dt_s, lag_steps, accel_std, position_std_m, attitude_std_rad,
                 imu_rot, imu_pos) -> None:  # fmt: skip
        if lag_steps < 1:
            raise ValueError(f"lag_steps must be >= 1, got {lag_steps}")
        self.dt_s, self.lag_steps = float(dt_s), int(lag_steps)
        self.imu_rot = np.ascontiguousarray(imu_rot, dtype=float)
        self.imu_pos = np.ascontiguousarray(imu_pos, dtype=float)
        fix_std = np.hypot(position_std_m, np.linalg.norm(self.imu_pos) * attitude_std_rad)
        self._smoother_args = (self.dt_s, float(accel_std), float(fix_std), self.lag_steps)
        self.smoother = self._new_smoother()
        self.buffer: deque[_Buffered] = deque()
        self._rot = np.eye(3)
        self._pos = np.zeros(3)
        self._has_attitude = False
        self._last_u = np.zeros(3)
        self.last_stamp = -1

    def error_ratio(self, fix_every: int):
        """f -> the fused acceleration's error PSD over the raw one (``fused_error_ratio``)
        with fixes every ``fix_every`` control steps, or None with nothing to fuse."""
        dt, accel_std, fix_std, lag = self._smoother_args
        if self.smoother is None:
            return None
        return fused_error_ratio(lag, dt, accel_std, fix_std, fix_every)

    def _new_smoother(self) -> FixedLagSmoother | None:
        """None where there is nothing to fuse (no accelerometer noise) or no fix noise."""
        dt, accel_std, fix_std, lag = self._smoother_args
        if not (accel_std > 0 and fix_std > 0):
            return None
        return FixedLagSmoother(dt, accel_std, fix_std, lag)

    def push(self, reading: Reading) -> Reading | None:
        """Take the readings of a new stamp (the next one: stamps must follow each other);
        return those of ``lag_steps`` earlier with the smoothed acceleration, or None while
        the buffer fills."""
        if self.last_stamp >= 0 and reading.stamp != self.last_stamp + 1:
            raise ValueError(
                f"motion_lag_s needs every control step: got stamp {reading.stamp} after "
                f"{self.last_stamp} (flush() first to end a flight)"
            )
        rot_wi, u_world, fix = self._to_world(reading)
        self.last_stamp = int(reading.stamp)
        if self.smoother is not None:
            if u_world is not None:
                self._last_u = u_world
            self.smoother.step(self._last_u, fix)
        self.buffer.append(_Buffered(reading, rot_wi, u_world))
        if len(self.buffer) <= self.lag_steps:
            return None
        smoothed = None if self.smoother is None else self.smoother.lagged_acceleration()
        return _corrected(self.buffer.popleft(), smoothed)

    def flush(self) -> list[Reading]:
        """Every buffered reading, oldest first, with the smoothed accelerations of the
        smoother's whole window (fixed-interval smoothing); the smoother starts afresh."""
        out = list(self.buffer)
        window = None if self.smoother is None else self.smoother.window_accelerations()
        self.buffer.clear()
        self.smoother = self._new_smoother()
        self.last_stamp = -1
        # Entry k is len(out) - 1 - k periods before the newest, the window's last.
        start = -len(out) if window is None else len(window) - len(out)
        return [
            _corrected(b, window[start + k] if start + k >= 0 else None) for k, b in enumerate(out)
        ]

    def _to_world(self, r: Reading):
        """This robot's attitude after stamp r (``update_attitude``); R_WI at mid-period, the
        reading u_W in world axes (None if unusable) and the IMU point's fix (None if none)."""
        usable = _finite(r.accel) and _finite(r.gyro)
        fix_given = r.pos is not None and r.quat is not None
        pos = np.asarray(r.pos, dtype=float) if fix_given else np.zeros(3)
        quat = np.asarray(r.quat, dtype=float) if fix_given else np.zeros(4)
        if fix_given and (pos.shape != (3,) or quat.shape != (4,)):
            raise ValueError("base_pos_world must be (3,) and base_quat_world (4,)")
        gyro = np.asarray(r.gyro, dtype=float) if usable else np.zeros(3)
        if not (self._has_attitude or fix_given):
            return None, None, None
        outcome = update_attitude(self._rot, self._pos, self.imu_rot, gyro, self.dt_s, pos,
                                  quat, fix_given)  # fmt: skip
        self._has_attitude |= outcome == FIX  # a bad first fix gives no attitude
        if not self._has_attitude:
            return None, None, None
        fix = self._pos + self._rot @ self.imu_pos if outcome == FIX else None
        if not usable:
            return None, None, fix
        w_base = self.imu_rot @ gyro
        rot_wi = self._rot @ exp_so3(-0.5 * self.dt_s * w_base) @ self.imu_rot
        return rot_wi, rot_wi @ np.asarray(r.accel, dtype=float), fix


def _corrected(b: _Buffered, smoothed: np.ndarray | None) -> Reading:
    """The buffered reading with a_I' = a_I + R_WI^T (a_W|N - u_W) (module docstring)."""
    if smoothed is None or b.u_world is None:
        return b.reading
    accel = np.asarray(b.reading.accel, dtype=float) + b.rot_world_imu.T @ (smoothed - b.u_world)
    return b.reading._replace(accel=accel)


@functools.lru_cache(maxsize=16)
def _ratio_table(lag_steps, dt_s, accel_std, position_std_m, fix_every) -> np.ndarray:
    """``smoother.lagged_error_psd_ratio`` on ``_RATIO_GRID_HZ`` (cached: one per set-up)."""
    ratio = lagged_error_psd_ratio(
        _RATIO_GRID_HZ, lag_steps, dt_s, accel_std, position_std_m, fix_every
    )
    ratio.setflags(write=False)
    return ratio


def fused_error_ratio(lag_steps, dt_s, accel_std, position_std_m, fix_every):
    """f (Hz) -> S_e(f) / S_a of the fused acceleration at ``lag_steps``
    (``smoother.lagged_error_psd_ratio``, tabulated on a log grid to 2 Hz and interpolated in
    log f; 1 above)."""
    ratio = _ratio_table(int(lag_steps), float(dt_s), float(accel_std), float(position_std_m),
                         int(fix_every))  # fmt: skip
    log_grid = np.log(_RATIO_GRID_HZ)
    return lambda f: np.interp(np.log(f), log_grid, ratio, left=ratio[0], right=1.0)


def coloured_lag_covariances(kernels, dt_s, update_every, n_lags, ratio=None) -> np.ndarray:
    """G (n_lags + 1, r, r) of the kernels' outputs (``kernels`` (r, span), per control step
    ``dt_s``) for an input of PSD S(f) = s^2 dt ratio(f) per unit per-sample variance s^2
    (None: white): G[L, a, b] = sum_m K_a[m] K_b[m + L u] in the white case
    (``motion.kernel_lag_covariances``), and in general the inverse transform of
    conj(K_a(f)) K_b(f) ratio(f), by FFT (zero-padded to hold every lag, and to at least
    ``_MIN_FFT`` periods: the coloured input's own correlation, tens of seconds below the
    crossover, would otherwise wrap around)."""
    shift = np.arange(n_lags + 1) * update_every
    n_fft = 1 << int(np.ceil(np.log2(max(2 * kernels.shape[1] + shift[-1], _MIN_FFT))))
    spec = np.fft.rfft(kernels, n_fft)
    weight = 1.0 if ratio is None else ratio(np.maximum(np.fft.rfftfreq(n_fft, dt_s), 1e-9))
    cross = np.fft.irfft(np.conj(spec)[:, None] * spec[None] * weight, n_fft)[:, :, shift]
    return np.ascontiguousarray(cross.transpose(2, 0, 1))


def flush_team(estimators) -> int:
    """End a flight of estimators running ``motion_lag_s``: step by step, each feeds its next
    buffered reading (``CargoEstimator.flush_steps``), the messages go straight to the others
    (no channel), and each processes. Returns the updates made."""
    done = 0
    for messages in itertools.zip_longest(*(est.flush_steps() for est in estimators)):
        for est in estimators:
            for msg in messages:
                if msg is not None and msg.sender != est.index:
                    est.receive(msg)
        done += sum(est.process() for est in estimators)
    return done
