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
pay one dispatch. Each (but ``quat_conj``) also has an out-parameter form ``<name>_into(out, ...)``
that writes its result into ``out`` (which must not share memory with an input, unless its
docstring says so) and allocates nothing: the returning form is that one writing into a new
array, so both give the same numbers. Kernels that run every control step use the ``_into``
forms with work arrays they allocate once per call (each numba heap allocation costs more than
a 3x3 product); the ``_into`` forms are inlined into their callers (``inline="always"``: a
call passing several arrays costs more than these bodies). ``matmul3`` and ``matvec3`` are the
3x3 products for compiled kernels (see their docstrings for why they exist). Batched forms,
where a caller needs them, are numpy one-liners on top (``rotation_matrices``).

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
    "cross3",
    "cross3_into",
    "exp_so3",
    "exp_so3_into",
    "log_so3",
    "log_so3_into",
    "mat_to_quat",
    "mat_to_quat_into",
    "matmul3",
    "matmul3_into",
    "matvec3",
    "matvec3_into",
    "quat_conj",
    "quat_mul",
    "quat_mul_into",
    "quat_to_mat",
    "quat_to_mat_into",
    "quat_to_rotvec",
    "quat_to_rotvec_into",
    "rotation_matrices",
    "rotvec_to_quat",
    "rotvec_to_quat_into",
    "skew",
    "skew_into",
]

_SMALL_ANGLE_RAD = 1e-12


@njit(cache=True, inline="always")
def matmul3_into(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """out = a b (3, 3) of two 3x3 matrices, C_ij = sum_k A_ik B_kj, any strides (a.T too).

    Inside numba, ``@`` on float64 arrays is a BLAS call whose fixed cost is several times the 27
    multiply-adds of a 3x3 product (and it needs contiguous operands); the small-matrix kernels
    of the step use this loop instead. Equal to ``a @ b`` to rounding."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


@njit(cache=True)
def matmul3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The product a b (3, 3) (``matmul3_into``)."""
    out = np.empty((3, 3))
    matmul3_into(out, a, b)
    return out


@njit(cache=True, inline="always")
def matvec3_into(out: np.ndarray, a: np.ndarray, v: np.ndarray) -> None:
    """out = a v (3,) of a 3x3 matrix and a 3-vector, any strides; ``matmul3_into``'s reason
    (a loop, not BLAS) holds here too. Equal to ``a @ v`` to rounding."""
    for i in range(3):
        out[i] = a[i, 0] * v[0] + a[i, 1] * v[1] + a[i, 2] * v[2]


@njit(cache=True)
def matvec3(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The product a v (3,) (``matvec3_into``)."""
    out = np.empty(3)
    matvec3_into(out, a, v)
    return out


@njit(cache=True, inline="always")
def cross3_into(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """out = a x b (3,) of two 3-vectors, any strides; ``matmul3_into``'s reason (numba's
    ``np.cross`` is a general broadcasting kernel) holds here too. Equal to ``np.cross``."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product a x b (3,) (``cross3_into``)."""
    out = np.empty(3)
    cross3_into(out, a, b)
    return out


@njit(cache=True, inline="always")
def skew_into(out: np.ndarray, v: np.ndarray) -> None:
    """out = [v]x (3, 3), the cross-product matrix of v (3,): ``skew(v) @ u == v x u``."""
    out[0, 0], out[0, 1], out[0, 2] = 0.0, -v[2], v[1]
    out[1, 0], out[1, 1], out[1, 2] = v[2], 0.0, -v[0]
    out[2, 0], out[2, 1], out[2, 2] = -v[1], v[0], 0.0


@njit(cache=True)
def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x (3, 3) of a vector v (3,) (``skew_into``)."""
    out = np.empty((3, 3))
    skew_into(out, v)
    return out


@njit(cache=True, inline="always")
def exp_so3_into(out: np.ndarray, rotvec: np.ndarray) -> None:
    """out = exp(rotvec) (3, 3), the rotation matrix of a rotation vector (3,) in radians
    (Rodrigues)."""
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    skew_into(out, rotvec)  # angle K, K = skew(u) with the axis u = rotvec / angle
    if angle < _SMALL_ANGLE_RAD:  # I + skew(rotvec)
        for i in range(3):
            for j in range(3):
                out[i, j] = (1.0 if i == j else 0.0) + out[i, j]
        return
    sin_a, cos_a = math.sin(angle), math.cos(angle)
    for i in range(3):  # cos(a) I + sin(a) K + (1 - cos(a)) u u^T, since K^2 = u u^T - I
        for j in range(3):
            axis_i, axis_j = rotvec[i] / angle, rotvec[j] / angle
            out[i, j] = sin_a * (out[i, j] / angle) + (1.0 - cos_a) * axis_i * axis_j
        out[i, i] += cos_a


@njit(cache=True)
def exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector (3,) in radians (``exp_so3_into``)."""
    out = np.empty((3, 3))
    exp_so3_into(out, rotvec)
    return out


@njit(cache=True, inline="always")
def _rotvec_of(out: np.ndarray, w: float, v: np.ndarray) -> None:
    """out = the rotation vector (angle in [0, pi]) of the quaternion (w, v); ``out`` may be
    ``v`` itself."""
    if w < 0.0:  # q and -q are one rotation; the positive-w one has the angle in [0, pi]
        w = -w
        for i in range(3):
            out[i] = -v[i]
    else:
        for i in range(3):
            out[i] = v[i]
    s = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2)
    if s < _SMALL_ANGLE_RAD * abs(w):
        for i in range(3):
            out[i] = 2.0 * out[i] / w  # first order: 2 atan2(s, w) / s -> 2 / w
        return
    scale = 2.0 * math.atan2(s, w) / s
    for i in range(3):
        out[i] = scale * out[i]


@njit(cache=True, inline="always")
def quat_to_rotvec_into(out: np.ndarray, quat: np.ndarray) -> None:
    """out = the rotation vector (3,), angle in [0, pi], of a quaternion (w, x, y, z) of any
    norm > 0."""
    _rotvec_of(out, quat[0], quat[1:4])


@njit(cache=True)
def quat_to_rotvec(quat: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), angle in [0, pi], of a quaternion (``quat_to_rotvec_into``)."""
    out = np.empty(3)
    quat_to_rotvec_into(out, quat)
    return out


@njit(cache=True, inline="always")
def rotvec_to_quat_into(out: np.ndarray, rotvec: np.ndarray) -> None:
    """out = the unit quaternion (w, x, y, z) of a rotation vector (3,) in radians."""
    angle = math.sqrt(rotvec[0] ** 2 + rotvec[1] ** 2 + rotvec[2] ** 2)
    out[0] = math.cos(0.5 * angle)
    if angle < _SMALL_ANGLE_RAD:
        for i in range(3):
            out[1 + i] = 0.5 * rotvec[i]
    else:
        scale = math.sin(0.5 * angle) / angle
        for i in range(3):
            out[1 + i] = scale * rotvec[i]


@njit(cache=True)
def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation vector (``rotvec_to_quat_into``)."""
    out = np.empty(4)
    rotvec_to_quat_into(out, rotvec)
    return out


@njit(cache=True, inline="always")
def quat_to_mat_into(out: np.ndarray, quat: np.ndarray) -> None:
    """out = the rotation matrix (3, 3) of a quaternion (w, x, y, z); the quaternion is
    normalised first (q / |q| = (w, v))."""
    norm = math.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    w = quat[0] / norm
    vv = (quat[1] / norm) ** 2 + (quat[2] / norm) ** 2 + (quat[3] / norm) ** 2
    skew_into(out, quat[1:4])  # |q| skew(v)
    for i in range(3):  # the equation of the module docstring, entry by entry
        for j in range(3):
            v_i, v_j = quat[1 + i] / norm, quat[1 + j] / norm
            out[i, j] = 2.0 * v_i * v_j + 2.0 * w * (out[i, j] / norm)
        out[i, i] += w * w - vv


@njit(cache=True)
def quat_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (w, x, y, z) (``quat_to_mat_into``)."""
    out = np.empty((3, 3))
    quat_to_mat_into(out, quat)
    return out


@njit(cache=True, inline="always")
def _shepperd(rot: np.ndarray, v: np.ndarray) -> float:
    """Shepperd's method on a rotation matrix (3, 3): a quaternion (w, v) of it, neither sign
    nor norm fixed; the vector part goes into ``v`` (3,), w is returned."""
    tr = rot[0, 0] + rot[1, 1] + rot[2, 2]
    if tr >= rot[0, 0] and tr >= rot[1, 1] and tr >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        w = 0.25 * s
        v[0] = (rot[2, 1] - rot[1, 2]) / s
        v[1] = (rot[0, 2] - rot[2, 0]) / s
        v[2] = (rot[1, 0] - rot[0, 1]) / s
    elif rot[0, 0] >= rot[1, 1] and rot[0, 0] >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + rot[0, 0] - rot[1, 1] - rot[2, 2], 0.0))
        w = (rot[2, 1] - rot[1, 2]) / s
        v[0] = 0.25 * s
        v[1] = (rot[0, 1] + rot[1, 0]) / s
        v[2] = (rot[0, 2] + rot[2, 0]) / s
    elif rot[1, 1] >= rot[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + rot[1, 1] - rot[0, 0] - rot[2, 2], 0.0))
        w = (rot[0, 2] - rot[2, 0]) / s
        v[0] = (rot[0, 1] + rot[1, 0]) / s
        v[1] = 0.25 * s
        v[2] = (rot[1, 2] + rot[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 + rot[2, 2] - rot[0, 0] - rot[1, 1], 0.0))
        w = (rot[1, 0] - rot[0, 1]) / s
        v[0] = (rot[0, 2] + rot[2, 0]) / s
        v[1] = (rot[1, 2] + rot[2, 1]) / s
        v[2] = 0.25 * s
    return w


@njit(cache=True, inline="always")
def _unit_positive(w: float, v: np.ndarray) -> float:
    """The quaternion (w, v) made unit with w >= 0, in place on ``v``; returns the new w."""
    if w < 0.0:
        w = -w
        for i in range(3):
            v[i] = -v[i]
    norm = math.sqrt(w**2 + v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    for i in range(3):
        v[i] = v[i] / norm
    return w / norm


@njit(cache=True, inline="always")
def mat_to_quat_into(out: np.ndarray, rot: np.ndarray) -> None:
    """out = the unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (3, 3) (Shepperd's
    method)."""
    v = out[1:4]
    out[0] = _unit_positive(_shepperd(rot, v), v)


@njit(cache=True)
def mat_to_quat(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (``mat_to_quat_into``)."""
    out = np.empty(4)
    mat_to_quat_into(out, rot)
    return out


@njit(cache=True, inline="always")
def log_so3_into(out: np.ndarray, rot: np.ndarray) -> None:
    """out = log(rot), the rotation vector (3,), angle in [0, pi], of a rotation matrix (3, 3):
    through its unit quaternion (``mat_to_quat_into`` then ``quat_to_rotvec_into``)."""
    w = _unit_positive(_shepperd(rot, out), out)
    _rotvec_of(out, w, out)


@njit(cache=True)
def log_so3(rot: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), angle in [0, pi], of a rotation matrix (``log_so3_into``)."""
    out = np.empty(3)
    log_so3_into(out, rot)
    return out


@njit(cache=True, inline="always")
def quat_mul_into(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """out = a * b, the Hamilton product of quaternions (w, x, y, z): rotation b first, then a."""
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]


@njit(cache=True)
def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (``quat_mul_into``)."""
    out = np.empty(4)
    quat_mul_into(out, a, b)
    return out


@njit(cache=True)
def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) of q (w, x, y, z)."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def rotation_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """``exp_so3`` of each row of an (N, 3) array of rotation vectors -> (N, 3, 3)."""
    rotvecs = np.asarray(rotvecs, dtype=float).reshape(-1, 3)
    return np.stack([exp_so3(v) for v in rotvecs]) if len(rotvecs) else np.zeros((0, 3, 3))
