"""The robots' own navigation filter: each robot's base pose and velocity from its own IMU and
localization fixes (no ground truth), for all robots at once.

Frames: ``rot`` (N, 3, 3) maps each base frame to the world (``estimator.geometry``
conventions); positions and velocities are in world axes, m and m/s; angular velocities in the
base frame, rad/s. One compiled kernel (numba) steps every robot.

Per robot and control period of length dt, with the period-mean gyro rate g and specific force
a (IMU frame, R_bi and r_i the IMU's rotation and position in the base frame):

- dead reckoning of the IMU point: w = R_bi g; R' = R exp(w dt);
  v' = v + dt R exp(w dt / 2) R_bi a (the force in the mid-period frame); p' = p + dt (v + v') / 2;
- position-velocity covariance C' = F C F^T + Q, F = [[1, dt], [0, 1]],
  Q = s_a^2 [[dt^4 / 4, dt^3 / 2], [dt^3 / 2, dt^2]] (isotropic: one 2x2 for all three axes);
  attitude variance c_att' = c_att + (s_g dt)^2;
- at a fix (R_fix, p_fix): gains k_att = c_att / (c_att + s_att^2), k_p = C00 / (C00 + s_p^2),
  k_v = C10 / (C00 + s_p^2); R <- R exp(k_att log(R^T R_fix)); with the innovation
  e = p_fix + R r_i - p: p <- p + k_p e, v <- v + k_v e;
- base origin: p_b = p - R r_i, v_b = v - R (w x r_i).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from astrocargo.envs.sensors import NoiseProfile, SensorReadings
from astrocargo.estimator.geometry import (
    cross3_into,
    exp_so3_into,
    log_so3_into,
    matmul3_into,
    matvec3_into,
    quat_to_mat,
    quat_to_mat_into,
)
from astrocargo.estimator.rne import RobotDescription

# Floors of the navigation filter's noise model, so the ideal profile stays well posed.
NAV_STD_FLOOR = 1e-9


@njit(cache=True, inline="always")
def _propagate(f, gyro, accel, dt_s, work_rot, work_vec):
    """Dead reckoning of one robot's IMU point over one period, in place on its filter record
    ``f`` (rot, point_pos, point_vel, w_base); ``work_rot`` (3, 3, 3), ``work_vec`` (3, 3):
    scratch."""
    exp_rot, product, rot_mid_imu = work_rot[0], work_rot[1], work_rot[2]
    w, rotvec, accel_world = work_vec[0], work_vec[1], work_vec[2]
    matvec3_into(w, f.imu_rot, gyro)
    for k in range(3):
        rotvec[k] = 0.5 * dt_s * w[k]
    exp_so3_into(exp_rot, rotvec)
    matmul3_into(product, f.rot, exp_rot)
    matmul3_into(rot_mid_imu, product, f.imu_rot)
    matvec3_into(accel_world, rot_mid_imu, accel)
    for k in range(3):
        rotvec[k] = dt_s * w[k]
    exp_so3_into(exp_rot, rotvec)
    matmul3_into(product, f.rot, exp_rot)
    f.rot[:] = product
    for k in range(3):  # v' = v + dt a, p' = p + dt (v + v') / 2
        vel_new = f.point_vel[k] + dt_s * accel_world[k]
        f.point_pos[k] += 0.5 * dt_s * (f.point_vel[k] + vel_new)
        f.point_vel[k] = vel_new
    f.w_base[:] = w


@njit(cache=True, inline="always")
def _blend_fix(f, fix_quat, fix_pos, gain_att, gain_pos, gain_vel, work_rot, work_vec):
    """One robot's Kalman blend of a localization fix, in place on its filter record ``f``:
    R, p, v; ``work_rot`` (3, 3, 3), ``work_vec`` (3, 3): scratch."""
    fix_rot, relative, new_rot = work_rot[0], work_rot[1], work_rot[2]
    correction, innovation = work_vec[0], work_vec[1]
    quat_to_mat_into(fix_rot, fix_quat)
    matmul3_into(relative, f.rot.T, fix_rot)
    log_so3_into(correction, relative)
    for k in range(3):
        correction[k] = gain_att * correction[k]
    exp_so3_into(relative, correction)
    matmul3_into(new_rot, f.rot, relative)
    f.rot[:] = new_rot
    matvec3_into(innovation, f.rot, f.imu_pos)
    for k in range(3):
        innovation[k] = fix_pos[k] + innovation[k] - f.point_pos[k]
        f.point_pos[k] = f.point_pos[k] + gain_pos * innovation[k]
        f.point_vel[k] = f.point_vel[k] + gain_vel * innovation[k]


# One robot's filter as a record: its state, then what it knows (IMU pose in the base frame, its
# noise model: Q00, Q01, Q11 and the variances). A record array (N,) of these crosses into the
# compiled step as one argument.
FILTER_DTYPE = np.dtype(
    [
        ("rot", "f8", (3, 3)),  # base frame -> world
        ("point_pos", "f8", 3),  # the IMU point, world, m
        ("point_vel", "f8", 3),  # m/s
        ("w_base", "f8", 3),  # base frame, rad/s
        ("cov", "f8", 4),  # position-velocity covariance C00, C01, C10, C11
        ("att_cov", "f8"),  # attitude variance, rad^2
        ("held_gyro", "f8", 3),  # the last IMU means (kept when a frame is missing)
        ("held_accel", "f8", 3),
        ("base_pos", "f8", 3),  # the base origin, world, m
        ("base_vel", "f8", 3),  # m/s
        ("imu_rot", "f8", (3, 3)),
        ("imu_pos", "f8", 3),
        ("q", "f8", 3),
        ("pos_var", "f8"),
        ("att_var", "f8"),
        ("gyro_step_var", "f8"),
    ],
    align=True,
)

_VIEW_FIELDS = FILTER_DTYPE.names[: FILTER_DTYPE.names.index("q")]  # the state and IMU pose


@njit(cache=True)
def navigate(filters, dt_s, gyro_now, accel_now, has_imu, fix_pos, fix_quat, has_fix, acting):
    """One period of every ``acting`` robot's filter (module docstring), in place:
    ``filters`` (N,) of ``FILTER_DTYPE``. ``held_gyro``, ``held_accel`` become this period's
    IMU means (``gyro_now``, ``accel_now``) where ``has_imu``; a fix where ``has_fix``."""
    work_rot, work_vec = np.empty((3, 3, 3)), np.empty((3, 3))  # the helpers' scratch
    arm, arm_vel, spin = work_vec[0], work_vec[1], work_vec[2]
    for i in range(filters.shape[0]):
        if not acting[i]:
            continue
        f = filters[i]
        if has_imu[i]:
            f.held_gyro[:], f.held_accel[:] = gyro_now[i], accel_now[i]
        _propagate(f, f.held_gyro, f.held_accel, dt_s, work_rot, work_vec)
        c00, c01, c10, c11 = f.cov[0], f.cov[1], f.cov[2], f.cov[3]
        a00, a01 = c00 + dt_s * c10, c01 + dt_s * c11  # first row of F C
        c00, c01 = a00 + a01 * dt_s + f.q[0], a01 + f.q[1]
        c10, c11 = c10 + c11 * dt_s + f.q[1], c11 + f.q[2]
        f.att_cov += f.gyro_step_var
        if has_fix[i]:
            gain_att = f.att_cov / (f.att_cov + f.att_var)
            gain_p, gain_v = c00 / (c00 + f.pos_var), c10 / (c00 + f.pos_var)
            _blend_fix(f, fix_quat[i], fix_pos[i], gain_att, gain_p, gain_v, work_rot, work_vec)
            f.att_cov *= 1.0 - gain_att
            c00, c01, c10, c11 = (
                c00 - gain_p * c00,
                c01 - gain_p * c01,
                c10 - gain_v * c00,
                (c11 - gain_v * c01),
            )
        f.cov[0], f.cov[1], f.cov[2], f.cov[3] = c00, c01, c10, c11
        matvec3_into(arm, f.rot, f.imu_pos)
        cross3_into(spin, f.w_base, f.imu_pos)
        matvec3_into(arm_vel, f.rot, spin)
        for k in range(3):  # base origin: p_b = p - R r_i, v_b = v - R (w x r_i)
            f.base_pos[k] = f.point_pos[k] - arm[k]
            f.base_vel[k] = f.point_vel[k] - arm_vel[k]


class BaseNavigator:
    """Every robot's estimate of its own base pose and velocity, from its own sensors only
    (module docstring): between localization fixes each dead-reckons with its gyro and
    accelerometer; at a fix it blends the fix in with Kalman gains from the noise profile the
    robot knows. ``filters`` (N,) of ``FILTER_DTYPE`` in robot index order; each of its fields
    up to ``imu_pos`` is also an attribute, an (N, ...) view (``rot``, ``base_pos``,
    ``base_vel``, ``w_base`` ...); ``q``, ``pos_var``, ``att_var``, ``gyro_step_var``: the noise
    model every robot's filter holds."""

    def __init__(self, robots: list[RobotDescription], dt_s: float, profile: NoiseProfile) -> None:
        self.dt_s = dt = float(dt_s)
        acc_var = max(profile.accel_std, NAV_STD_FLOOR) ** 2
        pos_var = max(profile.position_std_m, NAV_STD_FLOOR) ** 2
        att_var = max(profile.attitude_std_rad, NAV_STD_FLOOR) ** 2
        gyro_step_var = (max(profile.gyro_std, NAV_STD_FLOOR) * dt_s) ** 2
        q = acc_var * np.array([dt**4 / 4, dt**3 / 2, dt**2])  # Q00, Q01, Q11
        n = len(robots)
        self.filters = np.zeros(n, dtype=FILTER_DTYPE)
        self._bind_views()
        self.rot[:] = np.eye(3)
        self.imu_rot[:] = [r.imu_rot for r in robots]
        self.imu_pos[:] = [r.imu_pos for r in robots]
        # The noise model, the same for every robot: each record's copy, and the team's.
        for name, value in (("q", q), ("pos_var", pos_var), ("att_var", att_var),
                            ("gyro_step_var", gyro_step_var)):  # fmt: skip
            self.filters[name] = value
            setattr(self, name, value)

    def _bind_views(self) -> None:
        """Each state field of ``filters`` (up to ``imu_pos``) as an (N, ...) view attribute."""
        for name in _VIEW_FIELDS:
            setattr(self, name, self.filters[name])

    # A copy (copy.deepcopy, pickle) gets views of its own filters, not detached arrays.
    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in _VIEW_FIELDS}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._bind_views()

    def reset(self, readings: SensorReadings) -> None:
        """Start every robot at rest at its localization fix (each row must have one)."""
        if not readings.has_fix.all():
            raise ValueError("the navigator starts from readings with a localization fix")
        for i in range(len(self.rot)):
            self.rot[i] = quat_to_mat(np.ascontiguousarray(readings.base_quat_world[i]))
        # At rest: the IMU means, where the frame arrived.
        self.held_gyro[:] = np.where(readings.has_imu[:, None], readings.gyro_imu, 0.0)
        self.held_accel[:] = np.where(readings.has_imu[:, None], readings.accel_imu, 0.0)
        self.point_pos[:] = readings.base_pos_world + np.einsum(
            "nij,nj->ni", self.rot, self.imu_pos
        )
        self.w_base[:] = np.einsum("nij,nj->ni", self.imu_rot, self.held_gyro)
        self.point_vel[:] = 0.0
        self.cov[:] = 0.0
        self.cov[:, 0], self.cov[:, 3] = self.pos_var, NAV_STD_FLOOR**2
        self.att_cov[:] = self.att_var
        self.base_pos[:] = self.point_pos - np.einsum("nij,nj->ni", self.rot, self.imu_pos)
        self.base_vel[:] = -np.einsum("nij,nj->ni", self.rot, np.cross(self.w_base, self.imu_pos))

    def update(self, readings: SensorReadings, acting: np.ndarray) -> None:
        """Propagate the ``acting`` robots (bool (N,)) over one control period with their IMU
        means (the previous ones where a frame is missing); blend in their fixes. ``readings``
        has one row per robot index."""
        navigate(
            self.filters,
            self.dt_s,
            readings.gyro_imu,
            readings.accel_imu,
            readings.has_imu,
            readings.base_pos_world,
            readings.base_quat_world,
            readings.has_fix,
            acting,
        )
