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
raw difference. The filter is discretised exactly for an input that is linear between samples
(first-order hold): sensor samples are points of a smooth signal. A zero-order-hold discretisation
sees a staircase instead, whose jumps, always at the same phase of the sample, alias into a bias
of y'' (a ramp of 0.02 rad/s gave y'' = -6e-3 rad/s^2 at 2 Hz instead of 0).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from .rne import Kinematics, RobotDescription, propagate, v_cross, v_sub, wrench_transform


class StateVariableFilter:
    """Third-order critically damped low-pass with derivatives, vectorised over channels.

    ``step(u)`` takes one sample (n_channels,) and returns (y, yd, ydd), each (n_channels,).
    The first sample initialises the filter at rest at that value (no start-up transient on y).
    """

    def __init__(self, n_channels: int, dt_s: float, cutoff_hz: float) -> None:
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        if not (np.isfinite(cutoff_hz) and 0 < cutoff_hz < 0.5 / dt_s):
            raise ValueError(f"cutoff_hz must be in (0, {0.5 / dt_s}) (Nyquist), got {cutoff_hz}")
        # The -3 dB point of (w / (s + w))^3 is at w sqrt(2^(1/3) - 1).
        w = 2 * np.pi * cutoff_hz / np.sqrt(2 ** (1 / 3) - 1)
        a = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-(w**3), -3 * w**2, -3 * w]])
        b = np.array([0.0, 0.0, w**3])
        # Exact ZOH discretisation: expm of the augmented matrix [[A, B], [0, 0]] dt.
        # Exact first-order-hold discretisation: augment with the input and its constant slope.
        aug = np.zeros((5, 5))
        aug[:3, :3] = a
        aug[:3, 3] = b
        aug[3, 4] = 1.0
        e = expm(aug * dt_s)
        self.ad = e[:3, :3]
        self.b_value = e[:3, 3]  # weight of u_k
        self.b_slope = e[:3, 4] / dt_s  # weight of (u_k+1 - u_k)
        # One product per step: state_k+1 = [Ad | b_value - b_slope | b_slope] [state_k; u_k; u_k+1]
        # (numpy's per-call overhead on a few small arrays would dominate the separate terms).
        self._step_matrix = np.column_stack((self.ad, self.b_value - self.b_slope, self.b_slope))
        self.n_channels = int(n_channels)
        self.delay_s = 3.0 / w
        self._stacked = np.zeros((5, self.n_channels))  # [state (3 rows); u_prev; u]
        self.state = np.zeros((3, self.n_channels))
        self.started = False

    @property
    def u_prev(self) -> np.ndarray:
        """The previous input sample."""
        return self._stacked[3].copy()

    def step(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = np.asarray(u, dtype=float)
        if u.shape != (self.n_channels,):
            raise ValueError(f"filter input must have shape ({self.n_channels},), got {u.shape}")
        stacked = self._stacked
        if not self.started:
            self.state[0] = u
            stacked[0] = u
            self.started = True
        else:
            stacked[4] = u
            self.state = self._step_matrix @ stacked
            stacked[:3] = self.state
        stacked[3] = u
        return self.state[0], self.state[1], self.state[2]


class Preprocessor:
    """From raw IMU, encoders and the thrust command to the filtered inputs of the model.

    Per control step, ``step`` filters: the gyro and the IMU's specific force rotated into the base
    frame, the joint angles, and the commanded propulsion wrench (base frame, about B's origin).
    ``kinematics()`` then gives the link kinematics (IMU lever arm removed: the accelerometer
    measures the IMU point, a_imu = a_o + wd x r + w x (w x r)) and ``thrust()`` the filtered
    thrust; all share the filter's delay.
    """

    def __init__(self, robot: RobotDescription, dt_s: float, cutoff_hz: float = 1.0) -> None:
        self.robot = robot
        nj = robot.n_joints
        self._slices = {
            "gyro": slice(0, 3),
            "accel": slice(3, 6),
            "q": slice(6, 6 + nj),
            "thrust": slice(6 + nj, 12 + nj),
        }
        self._gyro, self._accel, self._q, self._thrust = self._slices.values()
        self._imu_pos = tuple(robot.imu_pos.tolist())
        self.filter = StateVariableFilter(12 + nj, dt_s, cutoff_hz)
        self._thrust_to_base = wrench_transform(robot.thrust_rot, robot.thrust_pos)
        # The filter's input from [gyro; accel; q; thrust command] in one product: the IMU
        # rotation twice, the identity, the thrust site's wrench transform, block-diagonal.
        self._to_input = np.zeros((12 + nj, 12 + nj))
        for block, rows in zip(
            (robot.imu_rot, robot.imu_rot, np.eye(nj), self._thrust_to_base),
            self._slices.values(),
            strict=True,
        ):
            self._to_input[rows, rows] = block
        self._y = self._yd = self._ydd = np.zeros(12 + nj)

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
        self._y, self._yd, self._ydd = self.filter.step(self._to_input @ raw)

    def base_and_joint_motion(self) -> tuple[np.ndarray, ...]:
        """Filtered (w, wd, acc of B's origin, q, qd, qdd), base frame."""
        return tuple(np.array(x) for x in self.base_and_joint_motion_rows())

    def base_and_joint_motion_rows(self) -> tuple[list[float], ...]:
        """``base_and_joint_motion`` as lists of floats."""
        w, wd = self._y[self._gyro].tolist(), self._yd[self._gyro].tolist()
        r = self._imu_pos
        acc_imu = self._y[self._accel].tolist()
        acc_origin = v_sub(v_sub(acc_imu, v_cross(wd, r)), v_cross(w, v_cross(w, r)))
        q = self._q
        return w, wd, acc_origin, self._y[q].tolist(), self._yd[q].tolist(), self._ydd[q].tolist()

    def kinematics(self) -> Kinematics:
        return propagate(self.robot, *self.base_and_joint_motion())

    def thrust(self) -> np.ndarray:
        return self._y[self._thrust].copy()

    @property
    def delay_s(self) -> float:
        return self.filter.delay_s
