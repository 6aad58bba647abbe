"""Rotations for the whole package: skew matrices, so(3) exp and log, unit quaternions.

Conventions, used everywhere in astrocargo:
- a rotation matrix ``R`` (3, 3) maps coordinates in a body frame to the parent (world) frame,
  ``v_world = R @ v_body``;
- a rotation vector ``phi`` (3,) is axis * angle, angle in radians, in [0, pi] for ``log_so3``;
- a quaternion ``q`` (4,) is MuJoCo's ``(w, x, y, z)``, scalar first, unit norm, and represents
  the same rotation as ``quat_to_mat(q)``;
- ``skew(v) @ u == np.cross(v, u)``.

Every function here takes and returns float64 numpy arrays of fixed shape and is compiled with
numba (``@njit(cache=True)``), so compiled kernels elsewhere call them directly and Python callers
pay one dispatch. ``matmul3`` and ``matvec3`` are the 3x3 products for compiled kernels (see
their docstrings for why they exist). Batched forms, where a caller needs them, are numpy
one-liners on top (``rotation_matrices``).

Equations:
- Rodrigues: ``exp(phi) = I + sin(a) K + (1 - cos(a)) K^2 = cos(a) I + sin(a) K + (1 - cos(a))
  u u^T``, ``a = |phi|``, ``u = phi / a``, ``K = skew(u)``.
- log: through the quaternion, ``phi = 2 atan2(|q_v|, q_w) q_v / |q_v|`` with ``q_w >= 0``, which is
  accurate at every angle including near 0 and pi (no division by sin(a)).
- quaternion to matrix: ``R = (w^2 - v.v) I + 2 v v^T + 2 w skew(v)`` for the normalised q.
- matrix to quaternion: Shepperd's method (the largest of w, x, y, z computed first).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "exp_so3",
    "matmul3",
    "matvec3",
    "cross3",
    "log_so3",
    "mat_to_quat",
    "quat_conj",
    "quat_mul",
    "quat_to_mat",
    "quat_to_rotvec",
    "rotation_matrices",
    "rotvec_to_quat",
    "skew",
]

_SMALL_ANGLE_RAD = 1e-12


@njit(cache=True)
def matmul3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The product a b (3, 3) of two 3x3 matrices, C_ij = sum_k A_ik B_kj, any strides (a.T too).

    Inside numba, ``@`` on float64 arrays is a BLAS call whose fixed cost is several times the 27
    multiply-adds of a 3x3 product (and it needs contiguous operands); the small-matrix kernels
    of the step use this loop instead. Equal to ``a @ b`` to rounding."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return out


@njit(cache=True)
def matvec3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The product a v (3,) of a 3x3 matrix and a 3-vector, any strides; ``matmul3``'s reason
    (a loop, not BLAS) holds here too. Equal to ``a @ v`` to rounding."""
    out = np.empty(3)
    for i in range(3):
        out[i] = a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]
    return out


@njit(cache=True)
def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product a x b (3,) of two 3-vectors, any strides; ``matmul3``'s reason (numba's
    ``np.cross`` is a general broadcasting kernel) holds here too. Equal to ``np.cross``."""
    return np.array(
        (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    )


@njit(cache=True)
def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x (3, 3) of a vector v (3,): ``skew(v) @ u == v x u``."""
    out = np.zeros((3, 3))
    out[0, 1], out[0, 2] = -v[2], v[1]
    out[1, 0], out[1, 2] = v[2], -v[0]
    out[2, 0], out[2, 1] = -v[1], v[0]
    return out


@njit(cache=True)
def exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector (3,) in radians (Rodrigues)."""
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    if angle < _SMALL_ANGLE_RAD:
        return np.eye(3) + skew(rotvec)
    axis = rotvec / angle
    sin_a, cos_a = math.sin(angle), math.cos(angle)
    k = skew(axis)
    out = np.empty((3, 3))
    for i in range(3):  # cos(a) I + sin(a) K + (1 - cos(a)) u u^T, since K^2 = u u^T - I
        for j in range(3):
            out[i, j] = sin_a * k[i, j] + (1.0 - cos_a) * axis[i] * axis[j]
        out[i, i] += cos_a
    return out


@njit(cache=True)
def quat_to_rotvec(quat: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), angle in [0, pi], of a quaternion (w, x, y, z) of any norm > 0."""
    w, v = quat[0], quat[1:4].copy()
    if w < 0.0:  # q and -q are one rotation; the positive-w one has the angle in [0, pi]
        w, v = -w, -v
    s = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    if s < _SMALL_ANGLE_RAD * abs(w):
        return 2.0 * v / w  # first order: 2 atan2(s, w) / s -> 2 / w
    return (2.0 * math.atan2(s, w) / s) * v


@njit(cache=True)
def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation vector (3,) in radians."""
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    out = np.empty(4)
    out[0] = math.cos(0.5 * angle)
    if angle < _SMALL_ANGLE_RAD:
        out[1:] = 0.5 * rotvec
    else:
        out[1:] = (math.sin(0.5 * angle) / angle) * rotvec
    return out


@njit(cache=True)
def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (w, x, y, z); the quaternion is normalised first."""
    q = quat / math.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    w, v = q[0], q[1:4]
    k = skew(v)
    out = np.empty((3, 3))
    for i in range(3):  # the equation of the module docstring, entry by entry
        for j in range(3):
            out[i, j] = 2.0 * v[i] * v[j] + 2.0 * w * k[i, j]
        out[i, i] += w * w - (v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    return out


@njit(cache=True)
def mat_to_quat(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (3, 3) (Shepperd's method)."""
    tr = rot[0, 0] + rot[1, 1] + rot[2, 2]
    q = np.empty(4)
    if tr >= rot[0, 0] and tr >= rot[1, 1] and tr >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q[0] = 0.25 * s
        q[1] = (rot[2, 1] - rot[1, 2]) / s
        q[2] = (rot[0, 2] - rot[2, 0]) / s
        q[3] = (rot[1, 0] - rot[0, 1]) / s
    elif rot[0, 0] >= rot[1, 1] and rot[0, 0] >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + rot[0, 0] - rot[1, 1] - rot[2, 2], 0.0))
        q[0] = (rot[2, 1] - rot[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (rot[0, 1] + rot[1, 0]) / s
        q[3] = (rot[0, 2] + rot[2, 0]) / s
    elif rot[1, 1] >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + rot[1, 1] - rot[0, 0] - rot[2, 2], 0.0))
        q[0] = (rot[0, 2] - rot[2, 0]) / s
        q[1] = (rot[0, 1] + rot[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (rot[1, 2] + rot[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + rot[2, 2] - rot[0, 0] - rot[1, 1], 0.0))
        q[0] = (rot[1, 0] - rot[0, 1]) / s
        q[1] = (rot[0, 2] + rot[2, 0]) / s
        q[2] = (rot[1, 2] + rot[2, 1]) / s
        q[3] = 0.25 * s
    if q[0] < 0.0:
        q = -q
    return q / math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)


@njit(cache=True)
def log_so3(rot: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), angle in [0, pi], of a rotation matrix (3, 3)."""
    return quat_to_rotvec(mat_to_quat(rot))


@njit(cache=True)
def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (w, x, y, z): rotation b first, then a."""
    out = np.empty(4)
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]
    return out


@njit(cache=True)
def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) of q (w, x, y, z)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def rotation_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """``exp_so3`` of each row of an (N, 3) array of rotation vectors -> (N, 3, 3)."""
    rotvecs = np.asarray(rotvecs, dtype=float).reshape(-1, 3)
    return np.stack([exp_so3(v) for v in rotvecs]) if len(rotvecs) else np.zeros((0, 3, 3))
