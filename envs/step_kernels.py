"""The part of a control step between the physics and the estimators as one compiled call:
the physics state's check (``physics.state_finite``), every robot's sensor readings
(``sensors.read_into``) with the faults' masks of the step, and the robots' navigation filters
(``navigation.navigate``). Each of these is the same kernel the separate calls run; the one call
passes their arrays across the Python boundary once (numba checks and unboxes every argument at
every call, which costs more than the arithmetic of two robots).
"""

from __future__ import annotations

from numba import njit

from astrocargo.envs.navigation import navigate
from astrocargo.envs.physics import state_finite
from astrocargo.envs.sensors import read_into


@njit(cache=True)
def sense_and_navigate(
    qpos, qvel, warnings, unstable, saved_qpos, saved_qvel,
    v0, r0, period_s, cvel, site_xpos, site_xmat, subtree_com, imu_index, sensordata, joint_adr,
    pos_adr, quat_adr, normals, noise_std, fix, rows, accel, gyro, joints, pos, quat, has_imu,
    has_fix, imu_ok, fix_ok, filters, acting, dt_s,
):  # fmt: skip
    """After the physics of a period: whether its state is finite (``state_finite``, which also
    saves qpos and qvel); the readings (``read_into``: the H robots of the world in ``rows``; their
    noise: the standard normals ``normals`` after the propulsion's first 6 H, as (H, draws), times
    ``noise_std``), whose IMU frames and fixes are then kept only where ``imu_ok`` / ``fix_ok``
    (bool (N,): what the faults leave); the navigation ``filters`` of the ``acting`` robots
    (``navigate``). Returns whether the state is finite."""
    h = rows.shape[0]
    draws = (normals.shape[0] - 6 * h) // h
    noise = noise_std[:draws] * normals[6 * h :].reshape(h, draws)
    finite = state_finite(qpos, qvel, warnings, unstable, saved_qpos, saved_qvel)
    read_into(
        v0, r0, period_s, cvel, site_xpos, site_xmat, subtree_com, imu_index, sensordata,
        joint_adr, pos_adr, quat_adr, noise, fix, rows, accel, gyro, joints, pos, quat,
        has_imu, has_fix,
    )  # fmt: skip
    for i in range(has_imu.shape[0]):
        has_imu[i] = has_imu[i] and imu_ok[i]
        has_fix[i] = has_fix[i] and fix_ok[i]
    navigate(filters, dt_s, gyro, accel, has_imu, pos, quat, has_fix, acting)
    return finite
