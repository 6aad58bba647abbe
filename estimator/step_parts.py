"""The compiled parts of one control step's common path (``per_step.estimator_step_arrays``,
module docstring there): the readings' checks, the servos' ripple taken off the accelerometer,
the attitude, the momentum form's chain and the actuation covariance carried into G. The
Python path of ``per_step.EstimatorInputs`` calls the same functions."""

from __future__ import annotations

import numpy as np
from numba import njit

from .checks import all_finite
from .geometry import exp_so3, matmul3, matvec3, quat_to_mat
from .momentum import sample_geometry_from_rate_filter
from .preprocess import first_order_hold_step
from .rne import grasp_from_base_kernel

# Outcomes of ``per_step.estimator_step`` (its first return value) and of ``update_attitude``.
NOT_USABLE, NO_FIX, FIX, BAD_FIX = range(4)


@njit(cache=True)
def any_nonzero(a: np.ndarray) -> bool:
    """Whether any entry is nonzero (NaN counts), as ``a.any()``."""
    for value in a.flat:
        if value != 0.0:
            return True
    return False


# ``ripple_case``'s outcomes.
RIPPLE_AT_REST, RIPPLE_UNUSABLE, RIPPLE_MOVING = range(3)


@njit(cache=True)
def ripple_case(rate, previous, q) -> int:
    """Whether the servos' ripple changes this step: RIPPLE_AT_REST when the targets' ``rate``
    and the ``previous`` ripple are zero (a NaN counts as nonzero), RIPPLE_UNUSABLE when the
    joint angles ``q`` or the rate are not finite, else RIPPLE_MOVING."""
    if not (any_nonzero(rate) or any_nonzero(previous)):
        return RIPPLE_AT_REST
    if not (all_finite(q) and all_finite(rate)):
        return RIPPLE_UNUSABLE
    return RIPPLE_MOVING


@njit(cache=True)
def servo_ripple_step(ripple_map, rate, previous, imu_rot, dt_s, accel):
    """The IMU point's ripple v_r = V rate (3,) m/s (B axes; V (3, n_joints) of
    ``momentum.servo_ripple_velocities``, ``rate`` rad/s) and the accelerometer's period mean
    less its change since the ``previous`` ripple, a - R_BI^T (v_r - v_r,prev) / dt (IMU axes,
    m/s^2)."""
    ripple = np.zeros(3)
    for i in range(3):
        for j in range(rate.shape[0]):
            ripple[i] += ripple_map[i, j] * rate[j]
    change = (ripple - previous) / dt_s
    return ripple, accel - matvec3(imu_rot.T, change)


@njit(cache=True)
def readings_usable(nj, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix) -> bool:
    """Every reading of the right shape and finite (the fix's shape too, when given)."""
    if accel.shape[0] != 3 or gyro.shape[0] != 3 or q.shape[0] != nj or thrust.shape[0] != 6:
        return False
    if has_fix and (fix_pos.shape[0] != 3 or fix_quat.shape[0] != 4):
        return False
    return all_finite(accel) and all_finite(gyro) and all_finite(q) and all_finite(thrust)


@njit(cache=True)
def pre_filter_input(pre_to_input, gyro, accel, q, thrust):
    """The pre-filter's input u = M [gyro; accel; q; thrust] (``pre_to_input`` M), the product
    in loops over the four readings (no stacked copy, no BLAS call)."""
    u = np.zeros(pre_to_input.shape[0])
    nj = q.shape[0]
    for i in range(u.shape[0]):
        for j in range(3):
            u[i] += pre_to_input[i, j] * gyro[j]
        for j in range(3):
            u[i] += pre_to_input[i, 3 + j] * accel[j]
        for j in range(nj):
            u[i] += pre_to_input[i, 6 + j] * q[j]
        for j in range(6):
            u[i] += pre_to_input[i, 6 + nj + j] * thrust[j]
    return u


@njit(cache=True)
def update_attitude(rot_world_base, pos_world_base, imu_rot, gyro, dt_s, fix_pos, fix_quat,
                    has_fix) -> int:  # fmt: skip
    """R_WB and p_WB in place from a usable fix (finite, |quat| > 0), else R_WB propagated by
    the gyro (rad/s, IMU axes) over dt_s; returns FIX, BAD_FIX or NO_FIX."""
    if has_fix:
        if all_finite(fix_quat) and all_finite(fix_pos) and np.linalg.norm(fix_quat) > 0:
            rot_world_base[:] = quat_to_mat(fix_quat)
            pos_world_base[:] = fix_pos
            return FIX
    rotvec = matvec3(imu_rot, gyro)
    for i in range(3):
        rotvec[i] *= dt_s
    rot_world_base[:] = matmul3(rot_world_base, exp_so3(rotvec))
    return BAD_FIX if has_fix else NO_FIX


@njit(cache=True)
def momentum_step(arrays, imu_pos, qd_var, rate_ad, rate_b_value, rate_b_slope, rate_held,
                  rate_state, rate_u_prev, prod_ad, prod_b_value, prod_b_slope, prod_held,
                  prod_state, prod_u_prev, u) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """One step of the momentum form's chain in place (``preprocess.Preprocessor``): the rate
    filter on the pre-filter's input ``u``, one momentum-form sample of its outputs
    (``momentum.sample_geometry_from_rate_filter``) into the product filter. Returns G at the rate
    filter's joint angles: the wrench map B -> G (6, 6) (``rne.grasp_from_base_kernel``) and
    G's origin in B (m)."""
    first_order_hold_step(
        rate_ad, rate_b_value, rate_b_slope, rate_held, rate_state, rate_u_prev, u
    )
    sample, geo = sample_geometry_from_rate_filter(arrays, imu_pos, rate_state, qd_var)
    first_order_hold_step(
        prod_ad, prod_b_value, prod_b_slope, prod_held, prod_state, prod_u_prev, sample
    )
    return geo.grasp_from_base, geo.grasp_pos


@njit(cache=True)
def actuation_cov_step(grasp_rot, grasp_pos, thrust_to_base, act_abs, act_rel, act_cov_sum,
                       thrust_command) -> float:  # fmt: skip
    """Add this step's actuation covariance, carried into G, to ``act_cov_sum``:
    T_GB T_BS diag(std^2) T_BS^T T_GB^T, std = abs + rel |command|; returns the lever |p_BG| m."""
    return actuation_cov_into(
        grasp_from_base_kernel(grasp_rot, grasp_pos), grasp_pos, thrust_to_base, act_abs,
        act_rel, act_cov_sum, thrust_command,
    )  # fmt: skip


@njit(cache=True)
def actuation_cov_into(grasp_from_base, grasp_pos, thrust_to_base, act_abs, act_rel, act_cov_sum,
                       thrust_command) -> float:  # fmt: skip
    """``actuation_cov_step`` given T_GB (``grasp_from_base`` (6, 6)) and p_BG (m):
    act_cov_sum_ij += sum_s A_is std_s^2 A_js with A = T_GB T_BS, in loops (a BLAS call costs
    more than these 6x6 products; equal to the matrix form to rounding)."""
    n_sites = thrust_to_base.shape[1]
    to_grasp = np.zeros((6, n_sites))
    for i in range(6):
        for k in range(6):
            for s in range(n_sites):
                to_grasp[i, s] += grasp_from_base[i, k] * thrust_to_base[k, s]
    var = np.empty(n_sites)
    for s in range(n_sites):
        var[s] = (act_abs[s] + act_rel[s] * abs(thrust_command[s])) ** 2
    for i in range(6):
        for j in range(6):
            total = 0.0
            for s in range(n_sites):
                total += to_grasp[i, s] * var[s] * to_grasp[j, s]
            act_cov_sum[i, j] += total
    lever_sq = 0.0
    for i in range(3):
        lever_sq += grasp_pos[i] ** 2
    return np.sqrt(lever_sq)
