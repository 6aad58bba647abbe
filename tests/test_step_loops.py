"""The per-step kernel's loop forms against the matrix products they replace (equal to rounding),
and the momentum chain's scratch: a pass in reused work arrays gives what a fresh pass gives."""

import numpy as np
from numba import njit

from astrocargo.estimator import momentum, step_parts
from astrocargo.estimator.geometry import exp_so3, skew
from astrocargo.estimator.preprocess import first_order_hold_step
from astrocargo.estimator.rne import grasp_from_base_kernel

RTOL = 1e-13


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def test_grasp_from_base_is_the_wrench_map_to_g():
    """T_GB = [[R^T, 0], [-R^T [p]x, R^T]]: f_G = R^T f, n_G = R^T (n - p x f)."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        rot, pos = exp_so3(rng.normal(size=3)), rng.normal(size=3)
        expected = np.zeros((6, 6))
        expected[:3, :3] = expected[3:, 3:] = rot.T
        expected[3:, :3] = -rot.T @ skew(pos)
        np.testing.assert_allclose(grasp_from_base_kernel(rot, pos), expected, rtol=0, atol=1e-15)
        wrench = rng.normal(size=6)
        force, moment = rot.T @ wrench[:3], rot.T @ (wrench[3:] - np.cross(pos, wrench[:3]))
        np.testing.assert_allclose(
            grasp_from_base_kernel(rot, pos) @ wrench, np.r_[force, moment], atol=1e-14
        )


def test_actuation_covariance_loops_equal_the_matrix_form():
    rng = np.random.default_rng(2)
    to_grasp, thrust_to_base = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    act_abs, act_rel, command = (
        rng.uniform(0.01, 0.1, 6),
        rng.uniform(0.0, 0.1, 6),
        rng.normal(size=6),
    )
    start = rng.normal(size=(6, 6))
    total = start.copy()
    pos = rng.normal(size=3)
    lever = step_parts.actuation_cov_into(
        to_grasp, pos, thrust_to_base, act_abs, act_rel, total, command
    )
    a = to_grasp @ thrust_to_base
    expected = start + a @ np.diag((act_abs + act_rel * np.abs(command)) ** 2) @ a.T
    np.testing.assert_allclose(total, expected, rtol=RTOL, atol=1e-15 * np.abs(expected).max())
    assert abs(lever - np.linalg.norm(pos)) <= 1e-15 * np.linalg.norm(pos)


def test_pre_filter_input_equals_the_stacked_product():
    rng = np.random.default_rng(3)
    nj = 2
    matrix = rng.normal(size=(9, 12 + nj))
    gyro, accel, q, thrust = (rng.normal(size=n) for n in (3, 3, nj, 6))
    expected = matrix @ np.concatenate((gyro, accel, q, thrust))
    np.testing.assert_allclose(
        step_parts.pre_filter_input(matrix, gyro, accel, q, thrust), expected, rtol=RTOL, atol=1e-14
    )


def test_first_order_hold_step_is_the_matrix_recursion():
    """x_k+1 = Ad x_k + b_value u_prev + b_slope (u - u_prev), held channels with u_prev = u."""
    rng = np.random.default_rng(4)
    n = 7
    ad, b_value, b_slope = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=3)
    held = np.array([True, False] * 3 + [True])
    state, u_prev, u = rng.normal(size=(3, n)), rng.normal(size=n), rng.normal(size=n)
    prev = np.where(held, u, u_prev)
    expected = ad @ state + np.outer(b_value, prev) + np.outer(b_slope, u - prev)
    first_order_hold_step(ad, b_value, b_slope, held, state, u_prev, u)
    np.testing.assert_allclose(state, expected, rtol=RTOL, atol=1e-14)
    np.testing.assert_array_equal(u_prev, u)


@njit(cache=True)
def _two_passes_in_one_work(arrays, imu_pos, first, second, qd_var):
    """momentum_pass_into on the rows ``first`` then ``second`` (each [w_base, acc, q, qd,
    thrust] stacked), in the same work arrays: the second pass's sample and T_GB."""
    n_links, nj = arrays.parent.shape[0], qd_var.shape[0]
    work, geo_work = momentum.momentum_work(n_links, 1 + nj, nj), momentum.geometry_work(n_links)
    for row in (first, second):
        out, geo = momentum.momentum_pass_into(
            work, geo_work, arrays, imu_pos, row[0:3], row[3:6], row[6 : 6 + nj],
            row[6 + nj : 6 + 2 * nj], row[6 + 2 * nj :], qd_var,
        )  # fmt: skip
    return out.copy(), geo.grasp_from_base.copy(), geo.total_mass


def test_momentum_pass_in_reused_work_equals_a_fresh_pass():
    """A pass that follows another in the same scratch (``momentum_work``, ``geometry_work``)
    gives the sample of a fresh ``momentum_pass_geometry`` bit for bit: nothing of the first
    pass is left in the arrays the second reads."""
    robot = _robot()
    arrays, imu_pos, nj = robot.arrays, np.asarray(robot.imu_pos, float), robot.n_joints
    rng = np.random.default_rng(5)
    first, second = rng.normal(size=(2, 12 + 2 * nj)) * 0.4
    qd_var = np.full(nj, 0.01)
    out, to_grasp, total_mass = _two_passes_in_one_work(arrays, imu_pos, first, second, qd_var)
    fresh, geo = momentum.momentum_pass_geometry(
        arrays, imu_pos, second[0:3], second[3:6], second[6 : 6 + nj],
        second[6 + nj : 6 + 2 * nj], second[6 + 2 * nj :], qd_var,
    )  # fmt: skip
    np.testing.assert_array_equal(out, fresh)
    np.testing.assert_array_equal(to_grasp, geo.grasp_from_base)
    assert total_mass == geo.total_mass == robot.arrays.mass.sum()
    assert not np.array_equal(out, momentum.momentum_pass_geometry(
        arrays, imu_pos, first[0:3], first[3:6], first[6 : 6 + nj],
        first[6 + nj : 6 + 2 * nj], first[6 + 2 * nj :], qd_var,
    )[0])  # fmt: skip
