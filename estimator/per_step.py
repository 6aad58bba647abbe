"""One control step of a ``CargoEstimator`` on its common path, compiled as one call.

When every reading of the step is present and finite, the estimator's per-step work is

1. the pre-filter step (``preprocess.Preprocessor``): u = T [gyro; accel; q; thrust], then
   x_k+1 = Ad x_k + b_value u_prev + b_slope (u - u_prev), u_prev = u on the held channels;
2. the attitude (base frame B in world): from the localization fix when there is a usable one,
   R_WB = R(quat), else propagated with the gyro, R_WB <- R_WB exp([R_BI w_imu dt]x);
3. on every ``regressor_every``-th step, the wrench balance in the grasp frame G from the
   filtered motion (``rne``: both Newton-Euler passes and the cargo's body regressor Y), the
   per-step covariance of the actuation noise carried into G,
       Sigma_G += T_GB T_BS diag(std^2) T_BS^T T_GB^T,   std = abs + rel |command|,
   and one step of the slow balance filter on [thrust_G; links_G; Y row by row].

``estimator_step`` does all of that in place on the estimator's arrays; its inputs are the
readings as they come (IMU body axes, rad, m, N and N m) and it changes nothing when a reading
is missing, non-finite or wrongly shaped (the estimator's Python path handles those). The
equations are those of ``preprocess``, ``rne`` and ``geometry``, whose compiled functions it
calls.
"""

from __future__ import annotations

import numpy as np
from numba import boolean, float64, int64, njit, types

from .geometry import exp_so3, quat_to_mat
from .preprocess import _first_order_hold_step
from .rne import RobotArrays, _links_and_regressor, point_acceleration

# Outcomes of `estimator_step` (its first return value).
NOT_USABLE, NO_FIX, FIX, BAD_FIX = range(4)


@njit(cache=True)
def _all_finite(a: np.ndarray) -> bool:
    for value in a.flat:
        if not np.isfinite(value):
            return False
    return True


@njit(cache=True)
def _usable(nj, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix) -> bool:
    """Every reading of the right shape and finite (the fix's shape too, when given)."""
    if accel.shape[0] != 3 or gyro.shape[0] != 3 or q.shape[0] != nj or thrust.shape[0] != 6:
        return False
    if has_fix and (fix_pos.shape[0] != 3 or fix_quat.shape[0] != 4):
        return False
    return _all_finite(accel) and _all_finite(gyro) and _all_finite(q) and _all_finite(thrust)


@njit(cache=True)
def filter_step(ad, b_value, b_slope, held, state, u_prev, u) -> None:
    """One step of a started ``StateVariableFilter`` in place: held channels take u_prev = u."""
    u_held = np.where(held, u, u_prev)
    state[:] = _first_order_hold_step(ad, b_value, b_slope, state, u_held, u)
    u_prev[:] = u


@njit(cache=True)
def update_attitude(rot_world_base, pos_world_base, imu_rot, gyro, dt_s, fix_pos, fix_quat,
                    has_fix) -> int:  # fmt: skip
    """R_WB and p_WB in place from a usable fix (finite, |quat| > 0), else R_WB propagated by
    the gyro (rad/s, IMU axes) over dt_s; returns FIX, BAD_FIX or NO_FIX."""
    if has_fix:
        if _all_finite(fix_quat) and _all_finite(fix_pos) and np.linalg.norm(fix_quat) > 0:
            rot_world_base[:] = quat_to_mat(fix_quat)
            pos_world_base[:] = fix_pos
            return FIX
    rot_world_base[:] = rot_world_base @ exp_so3(dt_s * (imu_rot @ gyro))
    return BAD_FIX if has_fix else NO_FIX


@njit(cache=True)
def balance_step(arrays, pre_y, pre_yd, pre_ydd, nj, imu_pos_neg, thrust_to_base, act_abs,
                 act_rel, act_cov_sum, thrust_command) -> tuple[np.ndarray, float]:  # fmt: skip
    """The balance of the filtered motion in G: [thrust_G; links_G; Y row by row] (72,), after
    adding this step's actuation covariance (grasp frame) to ``act_cov_sum``; and the lever
    |p_BG| m. The pre-filter's outputs are [gyro (3); accel (3); q (nj); thrust (6)]."""
    w, wd = pre_y[0:3], pre_yd[0:3]
    acc_base = point_acceleration(pre_y[3:6], w, wd, imu_pos_neg)
    q, qd, qdd = pre_y[6 : 6 + nj], pre_yd[6 : 6 + nj], pre_ydd[6 : 6 + nj]
    links_g, y, to_grasp_b, _, grasp_pos = _links_and_regressor(
        arrays, w, wd, acc_base, q, qd, qdd
    )
    thrust_g = to_grasp_b @ np.ascontiguousarray(pre_y[6 + nj : 12 + nj])
    to_grasp = to_grasp_b @ thrust_to_base
    std = act_abs + act_rel * np.abs(thrust_command)
    act_cov_sum += (to_grasp * std**2) @ to_grasp.T
    balance = np.concatenate((thrust_g, links_g, y.ravel()))
    return balance, np.sqrt(grasp_pos @ grasp_pos)


_V, _M, _T3 = float64[::1], float64[:, ::1], float64[:, :, ::1]
_BOOLS = boolean[::1]
_STEP_SIGNATURE = types.Tuple((int64, float64))(
    int64[::1], _M, _T3, _M, _V, _M, _T3, int64, _M, _V,  # RobotArrays
    _M, _M, _V, _V, _BOOLS, _V,  # pre-filter constants, IMU lever
    _M, _V, _V, _BOOLS,  # balance filter constants
    _M, _M, _V, _V, float64,  # IMU rotation, thrust site, actuation noise, dt
    _M, _V, _M, _V, _M, _M, _V,  # states, actuation covariance sum, attitude
    _V, _V, _V, _V, _V, _V, boolean, boolean,  # readings, flags
)


@njit(_STEP_SIGNATURE, cache=True)
def estimator_step(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, pre_to_input, pre_ad, pre_b_value, pre_b_slope, pre_held,
    imu_pos_neg, bal_ad, bal_b_value, bal_b_slope, bal_held, imu_rot, thrust_to_base, act_abs,
    act_rel, dt_s, pre_state, pre_u_prev, bal_state, bal_u_prev, act_cov_sum, rot_world_base,
    pos_world_base, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix, do_balance,
):  # fmt: skip
    """One common-path step (module docstring), in place on the filters' states and previous
    inputs, the actuation covariance sum and the attitude. Both filters must be started and the
    attitude known. Returns (outcome, lever |p_BG| m or NaN when no balance was filtered);
    outcome NOT_USABLE leaves everything unchanged."""
    nj = parent.shape[0] - 1
    if not _usable(nj, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix):
        return NOT_USABLE, np.nan
    raw = np.concatenate((gyro, accel, q, thrust))
    filter_step(pre_ad, pre_b_value, pre_b_slope, pre_held, pre_state, pre_u_prev,
                pre_to_input @ raw)  # fmt: skip
    outcome = update_attitude(
        rot_world_base, pos_world_base, imu_rot, gyro, dt_s, fix_pos, fix_quat, has_fix
    )
    if not do_balance:
        return outcome, np.nan
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    balance, lever = balance_step(
        arrays, pre_state[0], pre_state[1], pre_state[2], nj, imu_pos_neg, thrust_to_base,
        act_abs, act_rel, act_cov_sum, thrust,
    )  # fmt: skip
    filter_step(bal_ad, bal_b_value, bal_b_slope, bal_held, bal_state, bal_u_prev, balance)
    return outcome, lever
