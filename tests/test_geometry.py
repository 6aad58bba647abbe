"""estimator.geometry against independent references: MuJoCo's quaternion functions and the
matrix exponential of the skew matrix."""

import mujoco
import numpy as np
import pytest
from scipy.linalg import expm

from astrocargo.estimator import geometry as geo


def _rotvecs():
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            [0.0, 1e-14, 1e-7, 1e-3],
            rng.uniform(0, np.pi, 32),
            [np.pi - 1e-6, np.pi - 1e-10, np.pi, 3.0],
        ]
    )
    return axes * angles[:, None]


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    for v, u in rng.normal(size=(20, 2, 3)):
        np.testing.assert_allclose(geo.skew(v) @ u, np.cross(v, u), rtol=1e-14, atol=1e-15)


def test_small_products_equal_numpy_matmul_for_any_strides():
    rng = np.random.default_rng(1)
    for a, b in rng.normal(size=(20, 2, 3, 3)):
        v = b[:, 1]  # a strided column
        np.testing.assert_allclose(geo.matmul3(a, b), a @ b, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(geo.matmul3(a.T, b.T), a.T @ b.T, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(geo.matvec3(a, v), a @ v, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(geo.matvec3(a.T, v), a.T @ v, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("rotvec", list(_rotvecs()))
def test_exp_log_and_quaternions_agree_with_references(rotvec):
    rot = geo.exp_so3(rotvec)
    np.testing.assert_allclose(rot, expm(geo.skew(rotvec)), atol=1e-13)
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-14)
    quat = np.empty(4)
    angle = np.linalg.norm(rotvec)
    mujoco.mju_axisAngle2Quat(quat, rotvec / max(angle, 1e-300), angle)
    np.testing.assert_allclose(geo.rotvec_to_quat(rotvec), quat, atol=1e-15)
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    np.testing.assert_allclose(geo.quat_to_mat(quat), mat.reshape(3, 3), atol=1e-15)
    ref = np.empty(4)
    mujoco.mju_mat2Quat(ref, rot.reshape(9))
    q = geo.mat_to_quat(rot)
    assert abs(abs(q @ ref) - 1.0) < 1e-14 and q[0] >= 0
    back = geo.log_so3(rot)
    if angle < np.pi - 1e-6:
        np.testing.assert_allclose(back, rotvec, atol=1e-12)
    else:  # at pi, phi and -phi are one rotation
        np.testing.assert_allclose(geo.exp_so3(back), rot, atol=1e-12)
    np.testing.assert_allclose(geo.quat_to_rotvec(-quat), geo.quat_to_rotvec(quat), atol=1e-12)


def test_quaternion_product_composes_rotations():
    rng = np.random.default_rng(1)
    for a, b in rng.normal(size=(20, 2, 3)):
        qa, qb = geo.rotvec_to_quat(a), geo.rotvec_to_quat(b)
        ref = np.empty(4)
        mujoco.mju_mulQuat(ref, qa, qb)
        np.testing.assert_allclose(geo.quat_mul(qa, qb), ref, atol=1e-15)
        np.testing.assert_allclose(
            geo.quat_to_mat(geo.quat_mul(qa, qb)), geo.exp_so3(a) @ geo.exp_so3(b), atol=1e-14
        )
        np.testing.assert_allclose(geo.quat_mul(qa, geo.quat_conj(qa)), [1, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(
        geo.rotation_matrices(np.eye(3)), np.stack([geo.exp_so3(v) for v in np.eye(3)])
    )
