"""The update instant's producer kernels in scratch and loops: the sample's finite-difference
Jacobian in reused work arrays (``chain_modes.jacobian_work``) is the same forward difference of
fresh momentum-form samples, and the servo ripple's mass matrix in loops equals the matrix
products it replaces (to rounding)."""

import numpy as np
from numba import njit

from astrocargo.estimator import chain_modes, momentum
from astrocargo.estimator.geometry import skew

RTOL = 1e-13


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def _forward_difference(arrays, imu_pos, x, thrust, nj, step=1e-6):
    """d sample / dx by forward differences of fresh samples, one row at a time
    (``momentum.momentum_at`` at ``momentum.link_geometry`` of each row's joint angles)."""

    def sample(row):
        geo = momentum.link_geometry(arrays, np.ascontiguousarray(row[6 : 6 + nj]))
        at = momentum.momentum_at(
            arrays, imu_pos, geo, row[None, 0:3], row[None, 3:6], row[None, 6 + nj :], thrust
        )
        return at[0]

    base = sample(x)
    cols = []
    for k in range(x.shape[0]):
        stepped = x.copy()
        stepped[k] += step
        cols.append((sample(stepped) - base) / step)
    return np.stack(cols, axis=1)


def test_sample_jacobian_is_the_forward_difference_of_fresh_samples():
    """The Jacobian in its scratch (the batch at the angles' geometry, the angles' own rows) is
    the forward difference of samples computed one by one: the same arithmetic, bit for bit."""
    robot = _robot()
    arrays, imu_pos, nj = robot.arrays, np.asarray(robot.imu_pos, float), robot.n_joints
    rng = np.random.default_rng(11)
    for _ in range(3):
        x, thrust = rng.normal(size=6 + 2 * nj) * 0.5, rng.normal(size=6)
        got = chain_modes.sample_jacobian(
            arrays, imu_pos, x[0:3], x[3:6], x[6 : 6 + nj], x[6 + nj :], thrust
        )
        np.testing.assert_array_equal(got, _forward_difference(arrays, imu_pos, x, thrust, nj))


@njit
def _drift_twice(arrays, imu_pos, first, second, nj, step_s):
    """``drifting_jacobians_into`` at ``first`` then at ``second`` in one work."""
    work = chain_modes.jacobian_work(arrays.parent.shape[0], nj)
    jacs = np.empty((2, chain_modes.SIZE, 6 + 2 * nj))
    chain_modes.drifting_jacobians_into(jacs, work, arrays, imu_pos, first, nj, step_s)
    chain_modes.drifting_jacobians_into(jacs, work, arrays, imu_pos, second, nj, step_s)
    return jacs


def test_drifting_jacobians_in_reused_work_equal_the_central_difference():
    """A drift that follows another in the same scratch gives, bit for bit, what a fresh one
    gives, and that is J = (J+ + J-) / 2, dJ/dt = (J+ - J-) / step_s of ``sample_jacobian`` at
    the state moved by -+ step_s / 2 along its derivatives."""
    robot = _robot()
    arrays, imu_pos, nj = robot.arrays, np.asarray(robot.imu_pos, float), robot.n_joints
    rng = np.random.default_rng(12)
    first, second = rng.normal(size=(2, 3, 12 + nj)) * 0.4
    step_s = 0.05
    got = _drift_twice(arrays, imu_pos, first, second, nj, step_s)
    np.testing.assert_array_equal(
        got, chain_modes._drifting_jacobians(arrays, imu_pos, second, nj, step_s)
    )
    sides = []
    for sign in (-0.5, 0.5):
        value = second[0] + sign * step_s * second[1]
        rate = second[1] + sign * step_s * second[2]
        sides.append(chain_modes.sample_jacobian(
            arrays, imu_pos, value[0:3], value[3:6], value[6 : 6 + nj], rate[6 : 6 + nj],
            value[6 + nj :],
        ))  # fmt: skip
    np.testing.assert_array_equal(got[0], 0.5 * (sides[0] + sides[1]))
    np.testing.assert_array_equal(got[1], (sides[1] - sides[0]) / step_s)


def _body_jacobian(robot, geo, link, point):
    """[1, -[point]x, axis_k x (point - pos_k); 0, 1, axis_k] with numpy's products."""
    arrays = robot.arrays
    jac = np.zeros((6, 6 + robot.n_joints))
    jac[0:3, 0:3] = jac[3:6, 3:6] = np.eye(3)
    jac[0:3, 3:6] = -skew(point)
    k = link
    while k > 0:
        axis = geo.rot[k] @ arrays.joint_axis[k]
        jac[0:3, 5 + k] = np.cross(axis, point - geo.pos[k])
        jac[3:6, 5 + k] = axis
        k = arrays.parent[k]
    return jac


def _spatial(mass, first_moment, inertia):
    out = np.zeros((6, 6))
    out[0:3, 0:3] = mass * np.eye(3)
    out[0:3, 3:6], out[3:6, 0:3] = -skew(first_moment), skew(first_moment)
    out[3:6, 3:6] = inertia
    return out


def _mass_matrix(robot, q, cargo):
    """H = sum_k J_k^T M_k J_k over the links and the cargo, with numpy's products."""
    geo = momentum.link_geometry(robot.arrays, q)
    h = 0.0
    for k in range(robot.arrays.parent.shape[0]):
        jac = _body_jacobian(robot, geo, k, geo.pos[k] + geo.com_b[k])
        h = h + jac.T @ _spatial(robot.arrays.mass[k], np.zeros(3), geo.inertia_b[k]) @ jac
    c = cargo
    inertia_g = np.array([[c[4], c[7], c[8]], [c[7], c[5], c[9]], [c[8], c[9], c[6]]])
    rot = geo.grasp_rot
    jac = _body_jacobian(robot, geo, robot.arrays.grasp_link, geo.grasp_pos)
    return h + jac.T @ _spatial(c[0], rot @ c[1:4], rot @ inertia_g @ rot.T) @ jac


def test_generalised_inertia_loops_equal_the_matrix_products():
    """``generalised_inertia`` (congruences in loops) and ``servo_ripple_map`` from it equal
    the same sums of J^T M J by numpy's products and -(dt / 12) J_I H^-1 [0; 1]."""
    robot = _robot()
    arrays, imu_pos, nj = robot.arrays, np.asarray(robot.imu_pos, float), robot.n_joints
    rng = np.random.default_rng(13)
    for _ in range(5):
        q = rng.uniform(-1.5, 1.5, nj)
        cargo = np.r_[2.0, rng.normal(size=3) * 0.1, 0.3, 0.4, 0.5, rng.normal(size=3) * 0.02]
        expected = _mass_matrix(robot, q, cargo)
        got = momentum.generalised_inertia(arrays, q, cargo)
        np.testing.assert_allclose(got, expected, rtol=0, atol=RTOL * np.abs(expected).max())
        ripple = -(0.016 / 12.0) * np.linalg.solve(expected, np.eye(6 + nj)[:, 6:])
        at_imu = ripple[0:3] + np.cross(ripple[3:6].T, imu_pos).T
        got = momentum.servo_ripple_map(arrays, imu_pos, q, cargo, 0.016)
        np.testing.assert_allclose(got, at_imu, rtol=0, atol=1e-12 * np.abs(at_imu).max())
