"""Each robot's own navigation filter: its base pose and velocity from its own IMU and
localization fixes (no ground truth)."""

from __future__ import annotations

import mujoco
import numpy as np

from astrocargo.envs.sensors import NoiseProfile, SensorPacket
from astrocargo.envs.world import _quat_to_mat
from astrocargo.estimator.cargo_estimator import exp_so3_rows
from astrocargo.estimator.rne import (
    RobotDescription,
    as_rows,
    m_m,
    m_v,
    mt_m,
    v_add,
    v_cross,
    v_scale,
    v_sub,
)

# Floors of the navigation filter's noise model, so the ideal profile stays well posed.
NAV_STD_FLOOR = 1e-9


def rotvec_of_rows(rot: tuple) -> list[float]:
    """Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix given by its rows."""
    quat, vec = np.empty(4), np.empty(3)
    mujoco.mju_mat2Quat(quat, np.array(rot[0] + rot[1] + rot[2]))
    mujoco.mju_quat2Vel(vec, quat, 1.0)
    return vec.tolist()


class BaseNavigator:
    """One robot's estimate of its own base pose and velocity, from its own sensors only.

    Between localization fixes it dead-reckons: attitude with the gyro's period-mean rate,
    velocity and position of the IMU point with the accelerometer's period-mean specific force
    (exact for ideal readings: that mean is the change of the IMU point's velocity over the
    period). At a fix it blends in the fixed attitude and position with Kalman gains built from
    the noise profile the robot knows (isotropic, so one 2x2 covariance serves all three axes).

    The state is kept on Python floats (3-vectors and the rows of 3x3 matrices as tuples, with
    rne's helpers): a few 3x3 products per step, which numpy's per-call overhead would dominate.
    """

    def __init__(self, robot: RobotDescription, dt_s: float, profile: NoiseProfile) -> None:
        self.imu_rot = robot.imu_rot
        self.imu_pos = robot.imu_pos
        self._imu_rot, self._imu_pos = as_rows(robot.imu_rot), tuple(robot.imu_pos.tolist())
        self.dt_s = float(dt_s)
        acc_var = max(profile.accel_std, NAV_STD_FLOOR) ** 2
        self.pos_var = max(profile.position_std_m, NAV_STD_FLOOR) ** 2
        self.att_var = max(profile.attitude_std_rad, NAV_STD_FLOOR) ** 2
        self.gyro_step_var = (max(profile.gyro_std, NAV_STD_FLOOR) * dt_s) ** 2
        dt = self.dt_s
        # Position-velocity model x' = F x + noise, F = [[1, dt], [0, 1]], noise covariance
        # acc_var [[dt^4 / 4, dt^3 / 2], [dt^3 / 2, dt^2]] (q00, q01, q11).
        self._q = (acc_var * (dt**4 / 4), acc_var * (dt**3 / 2), acc_var * dt**2)

    def reset(self, packet: SensorPacket) -> None:
        """Start at rest at the packet's localization fix."""
        if packet.base_pos_world is None or packet.base_quat_world is None:
            raise ValueError("the navigator starts from a packet with a localization fix")
        self._rot = as_rows(_quat_to_mat(packet.base_quat_world))
        if packet.gyro_imu is None or packet.accel_imu is None:
            self._last_imu = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # at rest
        else:
            self._last_imu = (packet.gyro_imu.tolist(), packet.accel_imu.tolist())
        self._w = m_v(self._imu_rot, self._last_imu[0])
        self._p = v_add(packet.base_pos_world.tolist(), m_v(self._rot, self._imu_pos))
        self._v = (0.0, 0.0, 0.0)
        self._cov = (self.pos_var, 0.0, 0.0, NAV_STD_FLOOR**2)  # c00, c01, c10, c11
        self.att_cov = self.att_var

    def update(self, packet: SensorPacket) -> None:
        """Propagate over one control period with the packet's IMU means (the previous ones when
        the frame is missing); blend in its fix."""
        dt = self.dt_s
        if packet.gyro_imu is not None and packet.accel_imu is not None:
            self._last_imu = (packet.gyro_imu.tolist(), packet.accel_imu.tolist())
        gyro, accel = self._last_imu
        w = m_v(self._imu_rot, gyro)
        rot_mid_imu = m_m(m_m(self._rot, exp_so3_rows(v_scale(0.5 * dt, w))), self._imu_rot)
        self._rot = m_m(self._rot, exp_so3_rows(v_scale(dt, w)))
        v_new = v_add(self._v, v_scale(dt, m_v(rot_mid_imu, accel)))
        self._p = v_add(self._p, v_scale(0.5 * dt, v_add(self._v, v_new)))
        self._v = v_new
        self._w = w
        # cov <- F cov F^T + Q
        c00, c01, c10, c11 = self._cov
        q00, q01, q11 = self._q
        a00, a01 = c00 + dt * c10, c01 + dt * c11  # first row of F cov
        self._cov = (a00 + a01 * dt + q00, a01 + q01, c10 + c11 * dt + q01, c11 + q11)
        self.att_cov += self.gyro_step_var
        if packet.base_pos_world is None or packet.base_quat_world is None:
            return
        fix_rot = as_rows(_quat_to_mat(packet.base_quat_world))
        gain_att = self.att_cov / (self.att_cov + self.att_var)
        error = rotvec_of_rows(mt_m(self._rot, fix_rot))
        self._rot = m_m(self._rot, exp_so3_rows(v_scale(gain_att, error)))
        self.att_cov *= 1.0 - gain_att
        fixed_imu = v_add(packet.base_pos_world.tolist(), m_v(self._rot, self._imu_pos))
        innovation = v_sub(fixed_imu, self._p)
        c00, c01, c10, c11 = self._cov
        gain_p, gain_v = c00 / (c00 + self.pos_var), c10 / (c00 + self.pos_var)
        self._p = v_add(self._p, v_scale(gain_p, innovation))
        self._v = v_add(self._v, v_scale(gain_v, innovation))
        self._cov = (c00 - gain_p * c00, c01 - gain_p * c01, c10 - gain_v * c00, c11 - gain_v * c01)

    def state_rows(self) -> tuple[tuple, tuple, tuple, tuple]:
        """Base attitude (rows), position, velocity and angular velocity (base frame), floats."""
        rot, w, imu = self._rot, self._w, self._imu_pos
        base_pos = v_sub(self._p, m_v(rot, imu))
        base_vel = v_sub(self._v, m_v(rot, v_cross(w, imu)))
        return rot, base_pos, base_vel, w

    @property
    def rot(self) -> np.ndarray:
        return np.array(self._rot)

    @property
    def w_base(self) -> np.ndarray:
        return np.array(self._w)

    @property
    def base_pos(self) -> np.ndarray:
        return np.array(self.state_rows()[1])

    @property
    def base_vel(self) -> np.ndarray:
        return np.array(self.state_rows()[2])
