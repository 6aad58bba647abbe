"""Measurement pre-processing: one low-pass filter with derivatives for every signal.

The wrench balance needs angular and joint accelerations, which no sensor measures, and raw
accelerations are too noisy to enter a regressor (errors in variables: with Astrobee's
accelerations <= 0.0175 m/s^2 and 1e-3 m/s^2 accelerometer noise the signal-to-noise ratio per
sample is near 10). So every signal that enters the balance, kinematic or wrench, passes through
the *same* linear filter

    H(s) = w^3 / (s + w)^3        (critically damped, third order, cutoff ``cutoff_hz``)

realised as a state-variable filter whose state is (y, y', y''): the filtered signal and its first
two derivatives. Because the filter is linear and time invariant, y' and y'' are exactly the
filtered derivatives of the signal (d/dt H u = H du/dt), and all signals share the same delay
(3 / w s), so the balance stays consistent: H[thrust] = H[links] + H[A] pi, up to the products of
slow signals (w x I w, centripetal terms), which the filter passes unchanged to first order when
the motion lives well below the cutoff. Third order makes y'' a filter state, smooth, instead of a
raw difference.

The filter is discretised exactly for what each sample is. The encoders sample points of a smooth
signal, q(t_k): for them the input is linear between samples (first-order hold). A zero-order-hold
discretisation would see a staircase instead, whose jumps, always at the same phase of the sample,
alias into a bias of y'' (a ramp of 0.02 rad/s gave y'' = -6e-3 rad/s^2 at 2 Hz instead of 0).
The IMU's readings and the thrust command are *means over the control period* [t_k - dt, t_k]
(the IMU averages internally, the propulsion holds its command): their exact continuous-time
signal, as far as the samples know it, is the staircase that holds each mean over its own period
(it has the true signal's integral over every period), so they enter with a zero-order hold of the
new sample over the period it describes:
    x_k = A_d x_k-1 + B_0 u_k,   B_0 = int_0^dt e^{A s} b ds = b_value      (held channels)
    x_k = A_d x_k-1 + b_value u_k-1 + b_slope (u_k - u_k-1)                 (point samples)
Treating the means as point samples at t_k (first-order hold for every channel) places them dt/2
late against the encoders: the arm's motion then leads the base's reaction by dt/2 (8 ms at
62.5 Hz), and the balance, in which the two cancel, keeps dt/2 times the time derivative of the
arm's momentum rate. Under arm motion at the servos' rate limit (a triangle wave of the targets)
that residual biased the mass by 8-20 % with ideal sensors.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.linalg import expm, solve_discrete_lyapunov

from . import momentum as momentum_form
from .copies import deepcopy_state
from .rne import Kinematics, RobotDescription, point_acceleration, propagate

# The momentum form's rate filter (``Preprocessor``): fast enough that its departure from a pure
# delay, (f / f_c)^2, is small for the arm's harmonics, slow enough to keep the encoders' noise
# off the rates before they are multiplied.
DEFAULT_RATE_CUTOFF_HZ = 8.0


@njit(cache=True)
def first_order_hold_step(ad, b_value, b_slope, held, state, u_prev, u) -> None:
    """One step of every channel (column) in place: x_k+1 = Ad x_k + b_value u_k +
    b_slope (u_k+1 - u_k) into ``state`` (3, n), then u_prev <- u_k+1. A ``held`` channel
    passes u_k = u_k+1: x_k+1 = Ad x_k + b_value u_k+1 (zero-order hold of the new sample)."""
    free = np.empty(3)  # Ad x_k of one channel, in loops (a BLAS call costs more)
    for c in range(state.shape[1]):
        prev = u[c] if held[c] else u_prev[c]
        for i in range(3):
            free[i] = ad[i, 0] * state[0, c] + ad[i, 1] * state[1, c] + ad[i, 2] * state[2, c]
        for i in range(3):
            state[i, c] = free[i] + b_value[i] * prev + b_slope[i] * (u[c] - prev)
        u_prev[c] = u[c]


@functools.lru_cache(maxsize=64)
def _discretised(dt_s: float, cutoff_hz: float) -> np.ndarray:
    """exp(M dt) (5, 5) of the filter augmented with its input and the input's constant slope,
    M = [[A, B, 0], [0, 0, 1], [0, 0, 0]] (exact first-order-hold discretisation); the -3 dB point
    of (w / (s + w))^3 is at w sqrt(2^(1/3) - 1). Cached: every estimator of a run builds its
    filters at the same few (dt, cutoff) pairs. Read-only."""
    w = 2 * np.pi * cutoff_hz / np.sqrt(2 ** (1 / 3) - 1)
    aug = np.zeros((5, 5))
    aug[:3, :3] = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-(w**3), -3 * w**2, -3 * w]]
    aug[:3, 3] = [0.0, 0.0, w**3]
    aug[3, 4] = 1.0
    e = expm(aug * dt_s)
    e.setflags(write=False)
    return e


class StateVariableFilter:
    """Third-order critically damped low-pass with derivatives, vectorised over channels.

    Continuous form x' = A x + B u with x = (y, y', y''), A the companion matrix of (s + w)^3 and
    B = (0, 0, w^3); discretised exactly for an input linear between samples (first-order hold):

        x_k+1 = Ad x_k + b_value u_k + b_slope (u_k+1 - u_k),   Ad = exp(A dt),

    with b_value and b_slope the input columns of the exponential of the system augmented with
    the input and its slope. ``step(u)`` takes one sample (n_channels,) and returns (y, yd, ydd),
    each (n_channels,). The first sample puts the filter in its steady state for that constant
    input, x_ss = (I - Ad)^-1 b_value u = (u, 0, 0) (unit DC gain, zero derivatives): no start-up
    transient on y.

    ``held``: indices of the channels whose sample is the mean of the signal over the period that
    ends at it; they enter with a zero-order hold of the new sample, x_k+1 = Ad x_k + b_value
    u_k+1 (b_value = int_0^dt e^{A s} B ds is the zero-order-hold input column). The others are
    point samples (first-order hold). See the module docstring.
    """

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(
        self,
        n_channels: int,
        dt_s: float,
        cutoff_hz: float,
        held: slice | list[int] | np.ndarray | None = None,
    ) -> None:
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        if not (np.isfinite(cutoff_hz) and 0 < cutoff_hz < 0.5 / dt_s):
            raise ValueError(f"cutoff_hz must be in (0, {0.5 / dt_s}) (Nyquist), got {cutoff_hz}")
        # The -3 dB point of (w / (s + w))^3 is at w sqrt(2^(1/3) - 1).
        w = 2 * np.pi * cutoff_hz / np.sqrt(2 ** (1 / 3) - 1)
        e = _discretised(float(dt_s), float(cutoff_hz))
        self.ad = np.ascontiguousarray(e[:3, :3])
        self.b_value = np.ascontiguousarray(e[:3, 3])  # weight of u_k
        self.b_slope = e[:3, 4] / dt_s  # weight of (u_k+1 - u_k)
        self.n_channels = int(n_channels)
        self._held = np.zeros(self.n_channels, dtype=bool)
        if held is not None:
            self._held[held] = True
        self.delay_s = 3.0 / w
        self.state = np.zeros((3, self.n_channels))
        self._u_prev = np.zeros(self.n_channels)
        self.started = False

    @property
    def u_prev(self) -> np.ndarray:
        """The previous input sample."""
        return self._u_prev.copy()

    def step(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = np.asarray(u, dtype=float)
        if u.shape != (self.n_channels,):
            raise ValueError(f"filter input must have shape ({self.n_channels},), got {u.shape}")
        # The state and the previous input are updated in place (``per_step`` steps them too).
        if self.started:
            first_order_hold_step(
                self.ad, self.b_value, self.b_slope, self._held, self.state, self._u_prev, u
            )
        else:
            self.state[:] = 0.0
            self.state[0] = u
            self._u_prev[:] = u
            self.started = True
        return self.state[0].copy(), self.state[1].copy(), self.state[2].copy()

    def noise_gains(self) -> np.ndarray:
        """(g_y, g_yd, g_ydd) (3,): white noise of standard deviation s per sample leaves s * g on
        y, y' and y'' in steady state. g^2 is the energy of the impulse response, in closed form:
        a unit impulse at sample 0 leaves x_1 = b_slope and x_2 = Ad x_1 + b_value - b_slope, then
        x_k+1 = Ad x_k, so g^2 = x_1^2 + diag(P) with P = Ad P Ad^T + x_2 x_2^T (discrete
        Lyapunov equation)."""
        x1 = self.b_slope
        x2 = self.ad @ x1 + (self.b_value - self.b_slope)
        tail = solve_discrete_lyapunov(self.ad, np.outer(x2, x2))
        return np.sqrt(x1**2 + np.diag(tail))


@dataclass(frozen=True)
class BaseAndJointMotion:
    """Filtered motion of one instant, base frame B: what ``rne.propagate`` takes."""

    w_base: np.ndarray  # (3,) rad/s
    wd_base: np.ndarray  # (3,) rad/s^2
    acc_base: np.ndarray  # (3,) acceleration of B's origin, m/s^2
    q: np.ndarray  # (n_joints,) rad
    qd: np.ndarray  # (n_joints,) rad/s
    qdd: np.ndarray  # (n_joints,) rad/s^2


class Preprocessor:
    """From raw IMU, encoders and the thrust command to the filtered inputs of the model.

    Per control step, ``step`` filters: the gyro and the IMU's specific force rotated into the base
    frame, the joint angles, and the commanded propulsion wrench (base frame, about B's origin).
    ``motion()`` then gives the base and joint motion (IMU lever arm r removed: the accelerometer
    measures the IMU point, a_imu = a_o + wd x r + w x (w x r)), ``kinematics()`` the link
    kinematics and ``thrust()`` the filtered thrust; all share the filter's delay.

    Every step also forms the balance in momentum form (``momentum``): the same inputs pass a
    fast filter of the same kind (``rate_filter``, ``rate_cutoff_hz``; it gives the joint rates
    and takes the encoders' noise off the rates before they are multiplied), one momentum-form
    sample is built from its outputs (gyro, IMU-point acceleration, q, qd, thrust) and low-passed
    at ``cutoff_hz`` (``product_filter``): linear in the samples, so the slow filter downstream
    gives G[Z] = G'[P] + G[Q] for the cascade G of both. The encoders' noise (``encoder_std_rad``,
    white) that the rate filter leaves on qd, squared in Q's products of joint rates, is
    subtracted in expectation (``momentum.momentum_sample``'s ``qd_var``). ``grasp_pose`` is
    G's pose in B at the rate filter's joint angles. ``rate_cutoff_hz`` None:
    ``DEFAULT_RATE_CUTOFF_HZ``, or a quarter of the sample rate when that is lower.
    """

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(
        self,
        robot: RobotDescription,
        dt_s: float,
        cutoff_hz: float = 1.0,
        encoder_std_rad: float = 0.0,
        rate_cutoff_hz: float | None = None,
    ) -> None:
        self.robot = robot
        nj = robot.n_joints
        self._gyro, self._accel = slice(0, 3), slice(3, 6)
        self._q, self._thrust = slice(6, 6 + nj), slice(6 + nj, 12 + nj)
        self._imu_pos_neg = -np.asarray(robot.imu_pos, dtype=float)
        # The IMU's readings and the thrust command are period means (held); the encoders are
        # point samples.
        held = [*range(0, 6), *range(6 + nj, 12 + nj)]
        self.filter = StateVariableFilter(12 + nj, dt_s, cutoff_hz, held=held)
        # The filter's input from [gyro; accel; q; thrust command] in one product: the IMU
        # rotation twice, the identity, the thrust site's wrench transform, block-diagonal.
        self._to_input = np.zeros((12 + nj, 12 + nj))
        blocks = (robot.imu_rot, robot.imu_rot, np.eye(nj), robot.thrust_to_base)
        rows = (self._gyro, self._accel, self._q, self._thrust)
        for block, row in zip(blocks, rows, strict=True):
            self._to_input[row, row] = block
        rate_hz = (
            min(DEFAULT_RATE_CUTOFF_HZ, 0.25 / dt_s) if rate_cutoff_hz is None else rate_cutoff_hz
        )
        self.rate_cutoff_hz = float(rate_hz)
        self.rate_filter = StateVariableFilter(12 + nj, dt_s, rate_hz, held=held)
        # Its y' of white encoder noise: variance (s g_yd)^2 per joint (``noise_gains``).
        self.rate_noise_gains = self.rate_filter.noise_gains()
        self.qd_var = np.full(nj, (encoder_std_rad * self.rate_noise_gains[1]) ** 2)
        # The products' samples, linear from here on (first-order hold).
        self.product_filter = StateVariableFilter(momentum_form.SIZE, dt_s, cutoff_hz)
        self._imu_pos = np.ascontiguousarray(robot.imu_pos, dtype=float)
        self.grasp_pose = (np.eye(3), np.zeros(3))

    def step(
        self,
        accel_imu: np.ndarray,
        gyro_imu: np.ndarray,
        joint_pos_rad: np.ndarray,
        thrust_command: np.ndarray,
    ) -> None:
        self.step_raw(self.raw_input(accel_imu, gyro_imu, joint_pos_rad, thrust_command))

    @staticmethod
    def raw_input(
        accel_imu: np.ndarray,
        gyro_imu: np.ndarray,
        joint_pos_rad: np.ndarray,
        thrust_command: np.ndarray,
    ) -> np.ndarray:
        """The readings of one step as one vector [gyro; accel; q; thrust] (``step_raw``)."""
        return np.concatenate((gyro_imu, accel_imu, joint_pos_rad, thrust_command))

    def step_raw(self, raw: np.ndarray) -> None:
        """``step`` with the readings already in one vector (``raw_input``)."""
        u = self._to_input @ raw
        self.filter.step(u)
        self.rate_filter.step(u)
        sample, rot, pos = momentum_form._sample_from_rate_filter(
            *self.robot.arrays, self._imu_pos, self.rate_filter.state, self.qd_var
        )
        self.product_filter.step(sample)
        self.grasp_pose = (rot, pos)

    def motion(self) -> BaseAndJointMotion:
        """Filtered base and joint motion, base frame (copies of the filter's state)."""
        y, yd, ydd = self.filter.state.copy()
        w, wd = y[self._gyro], yd[self._gyro]
        # a_o = a_imu - wd x r - w x (w x r): the IMU point's acceleration at the lever -r.
        acc_origin = point_acceleration(y[self._accel], w, wd, self._imu_pos_neg)
        q = self._q
        return BaseAndJointMotion(w, wd, acc_origin, y[q], yd[q], ydd[q])

    def kinematics(self) -> Kinematics:
        m = self.motion()
        return propagate(self.robot, m.w_base, m.wd_base, m.acc_base, m.q, m.qd, m.qdd)

    def thrust(self) -> np.ndarray:
        return self.filter.state[0, self._thrust].copy()

    @property
    def delay_s(self) -> float:
        return self.filter.delay_s
