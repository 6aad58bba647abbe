"""Inertial parameters of one rigid body: conversions, consistency checks and error metrics.

Conventions, used by every function below:

- Standard parameter vector, SI units (kg, kg m, kg m^2), all in one body frame with origin o::

      pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]

  with h = m c (c the centre of mass from o) and I_o the inertia tensor about o. Off-diagonals are
  the tensor entries, e.g. I_xy = -sum m x y. Parallel axis: I_o = I_c + m [c]x^T [c]x.
- Inertia 6-vectors are ordered [xx, yy, zz, xy, xz, yz].
- Pseudo-inertia J = [[S, h], [h^T, m]] with S = 0.5 tr(I_o) 1 - I_o (second moment of mass about
  o). The body is physically realisable exactly when J is positive definite.
- Log-Cholesky coordinates (Rucker and Wensing 2022), unconstrained::

      eta = (alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3)
      U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]]
      J = U U^T,  so m = e^(2 alpha) and c = (t1, t2, t3).

Every function is batched: it takes arrays of shape (..., 10) (or (..., 4, 4), (..., 3, 3)) and
returns the same leading shape, without Python loops over the batch (a UKF calls these on all its
sigma points every update). Only numpy is used, and numba for the error metrics of
`estimate_errors`, which the env evaluates at every estimator update.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = [
    "InertialParams",
    "check_physical",
    "com_error_m",
    "estimate_errors",
    "inertia_to_vec",
    "log_cholesky_jacobian",
    "log_cholesky_to_params",
    "mass_com_inertia_from_params",
    "mass_rel_error",
    "params_from_mass_com_inertia",
    "params_to_log_cholesky",
    "params_to_pseudo_inertia",
    "physical_violation",
    "principal_moments",
    "principal_rel_errors",
    "pseudo_inertia_distance",
    "pseudo_inertia_to_params",
    "pseudo_inertia_transform",
    "transform_params",
    "vec_to_inertia",
    "project_physical",
]

# Row and column of each inertia 6-vector entry [xx, yy, zz, xy, xz, yz] in the 3x3 tensor, and
# the 6-vector index of each of the nine tensor entries (row-major).
_VEC_ROWS = np.array([0, 1, 2, 0, 0, 1])
_VEC_COLS = np.array([0, 1, 2, 1, 2, 2])
_TENSOR_TO_VEC = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])
_VEC_IS_DIAGONAL = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])

_SYMMETRY_RTOL = 1e-9
_ROTATION_ATOL = 1e-6

# pi / m is a quadratic form in w = (e^d1, e^d2, e^d3, s12, s23, s13, t1, t2, t3, 1), i.e. eta[1:]
# with the d's exponentiated and a constant 1 appended. The table is the map pi(eta) of the
# log-Cholesky parameterisation (Rucker and Wensing 2022) line by line:
# each pi entry lists (coefficient, factor, factor).
_W_NAMES = ("e^d1", "e^d2", "e^d3", "s12", "s23", "s13", "t1", "t2", "t3", "1")
_PI_OVER_MASS_TERMS = (
    [(1.0, "1", "1")],  # m / m
    [(1.0, "t1", "1")],  # h_x / m = c_x
    [(1.0, "t2", "1")],
    [(1.0, "t3", "1")],
    # I_xx = s23^2 + t2^2 + t3^2 + e^(2 d2) + e^(2 d3)
    [(1.0, n, n) for n in ("s23", "t2", "t3", "e^d2", "e^d3")],
    # I_yy = s12^2 + s13^2 + t1^2 + t3^2 + e^(2 d1) + e^(2 d3)
    [(1.0, n, n) for n in ("s12", "s13", "t1", "t3", "e^d1", "e^d3")],
    # I_zz = s12^2 + s13^2 + s23^2 + t1^2 + t2^2 + e^(2 d1) + e^(2 d2)
    [(1.0, n, n) for n in ("s12", "s13", "s23", "t1", "t2", "e^d1", "e^d2")],
    [(-1.0, "s12", "e^d2"), (-1.0, "s13", "s23"), (-1.0, "t1", "t2")],  # I_xy
    [(-1.0, "s13", "e^d3"), (-1.0, "t1", "t3")],  # I_xz
    [(-1.0, "s23", "e^d3"), (-1.0, "t2", "t3")],  # I_yz
)


def _quadratic_forms() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The table as pi / m = w^T Q[k] w, Q (10, 10, 10) symmetric, and as a sum of products.

    Products: pi / m = (w[..., a] * w[..., b]) @ c over the distinct pairs a <= b that occur.
    """
    q = np.zeros((10, 10, 10))
    for k, terms in enumerate(_PI_OVER_MASS_TERMS):
        for coefficient, a_name, b_name in terms:
            a, b = _W_NAMES.index(a_name), _W_NAMES.index(b_name)
            q[k, a, b] += 0.5 * coefficient
            q[k, b, a] += 0.5 * coefficient
    pair_a, pair_b = np.nonzero(np.triu(np.abs(q).sum(axis=0)))
    pair_to_pi = np.where(pair_a == pair_b, 1.0, 2.0)[:, None] * q[:, pair_a, pair_b].T
    return q, pair_a, pair_b, pair_to_pi


_Q, _PAIR_A, _PAIR_B, _PAIR_TO_PI = _quadratic_forms()
_Q_ROWS = _Q.reshape(100, 10).copy()  # (this @ w).reshape(10, 10)[k] = Q[k] w


# --------------------------------------------------------------------------- input checks


def _as_array(x: object, trailing_shape: tuple[int, ...], name: str) -> np.ndarray:
    """Return x as a finite float array of shape (..., *trailing_shape), or raise ValueError."""
    a = np.asarray(x, dtype=float)
    n = len(trailing_shape)
    if a.ndim < n or a.shape[a.ndim - n :] != trailing_shape:
        expected = ", ".join(["..."] + [str(s) for s in trailing_shape])
        raise ValueError(f"{name} must have shape ({expected}), got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite, got non-finite entries (nan or inf)")
    return a


def _as_single(x: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    """Like _as_array, but for exactly one item of the given shape (no batch)."""
    a = np.asarray(x, dtype=float)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {a.shape}")
    return _as_array(a, shape, name)


def _check_symmetric(a: np.ndarray, name: str) -> None:
    asymmetry = np.abs(a - np.swapaxes(a, -1, -2)).max(initial=0.0)
    scale = np.abs(a).max(initial=0.0)
    if asymmetry > _SYMMETRY_RTOL * (1.0 + scale):
        raise ValueError(f"{name} must be symmetric, got asymmetry {asymmetry:.3g}")


def _check_rotation(rotation: np.ndarray) -> None:
    eye = np.eye(3)
    orthogonality = np.abs(np.swapaxes(rotation, -1, -2) @ rotation - eye).max(initial=0.0)
    if orthogonality > _ROTATION_ATOL or (np.linalg.det(rotation) <= 0.0).any():
        raise ValueError(
            "rotation must be a proper rotation matrix (R^T R = 1 within "
            f"{_ROTATION_ATOL}, det R = +1), got |R^T R - 1| = {orthogonality:.3g}"
        )


# --------------------------------------------------------------------------- small helpers


def _vec_to_inertia(v: np.ndarray) -> np.ndarray:
    return v[..., _TENSOR_TO_VEC].reshape(v.shape[:-1] + (3, 3))


def inertia_to_vec(inertia: np.ndarray) -> np.ndarray:
    """Symmetric (..., 3, 3) inertia tensor -> (..., 6) vector [xx, yy, zz, xy, xz, yz]."""
    inertia = _as_array(inertia, (3, 3), "inertia")
    _check_symmetric(inertia, "inertia")
    return inertia[..., _VEC_ROWS, _VEC_COLS]


def vec_to_inertia(v: np.ndarray) -> np.ndarray:
    """(..., 6) vector [xx, yy, zz, xy, xz, yz] -> symmetric (..., 3, 3) inertia tensor."""
    return _vec_to_inertia(_as_array(v, (6,), "inertia vector"))


# --------------------------------------------------------------------------- standard parameters


def params_from_mass_com_inertia(
    mass: np.ndarray | float, com: np.ndarray, inertia_com: np.ndarray
) -> np.ndarray:
    """Standard parameters pi (..., 10) from mass (kg), com c (m) and inertia about c (kg m^2).

    Uses the parallel axis theorem I_o = I_c + m [c]x^T [c]x = I_c + m (|c|^2 1 - c c^T).
    The leading shapes broadcast together.
    """
    mass = _as_array(mass, (), "mass")
    com = _as_array(com, (3,), "com")
    inertia_com = _as_array(inertia_com, (3, 3), "inertia_com")
    _check_symmetric(inertia_com, "inertia_com")
    m = mass[..., None]
    # m [c]x^T [c]x = m (|c|^2 1 - c c^T), as a 6-vector.
    com_squared = np.sum(com * com, axis=-1, keepdims=True)
    shift = m * (com_squared * _VEC_IS_DIAGONAL - com[..., _VEC_ROWS] * com[..., _VEC_COLS])
    inertia_o = inertia_com[..., _VEC_ROWS, _VEC_COLS] + shift
    batch = np.broadcast_shapes(mass.shape, com.shape[:-1], inertia_o.shape[:-1])
    pi = np.empty(batch + (10,))
    pi[..., :1] = m
    pi[..., 1:4] = m * com
    pi[..., 4:10] = inertia_o
    return pi


def _mass_com_inertia(pi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mass = pi[..., 0]
    com = pi[..., 1:4] / mass[..., None]
    h = pi[..., 1:4]
    shift = np.sum(h * h, axis=-1)[..., None, None] * np.eye(3) - h[..., :, None] * h[..., None, :]
    inertia_com = _vec_to_inertia(pi[..., 4:10]) - shift / mass[..., None, None]
    return mass, com, inertia_com


def mass_com_inertia_from_params(pi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split pi (..., 10) into mass (...) kg, com (..., 3) m and inertia about the com (..., 3, 3).

    Raises ValueError if a mass is not positive (the centre of mass is then undefined).
    """
    pi = _as_array(pi, (10,), "pi")
    if (pi[..., 0] <= 0.0).any():
        raise ValueError(
            f"mass must be positive to define a centre of mass, got min mass {pi[..., 0].min()} kg"
        )
    return _mass_com_inertia(pi)


def _pseudo_inertia_by_definition(pi: np.ndarray) -> np.ndarray:
    inertia_o = _vec_to_inertia(pi[..., 4:10])
    trace = pi[..., 4] + pi[..., 5] + pi[..., 6]
    j = np.empty(pi.shape[:-1] + (4, 4))
    j[..., :3, :3] = 0.5 * trace[..., None, None] * np.eye(3) - inertia_o
    j[..., :3, 3] = pi[..., 1:4]
    j[..., 3, :3] = pi[..., 1:4]
    j[..., 3, 3] = pi[..., 0]
    return j


def _params_from_pseudo_inertia_by_definition(j: np.ndarray) -> np.ndarray:
    second_moment = j[..., :3, :3]
    trace = np.trace(second_moment, axis1=-2, axis2=-1)
    inertia_o = trace[..., None, None] * np.eye(3) - second_moment
    pi = np.empty(j.shape[:-2] + (10,))
    pi[..., 0] = j[..., 3, 3]
    pi[..., 1:4] = j[..., :3, 3]
    pi[..., 4:10] = inertia_o[..., _VEC_ROWS, _VEC_COLS]
    return pi


# J is linear in pi (and back): one matrix product is several times faster on small batches than
# the definitions above, from which the maps are built.
_PI_TO_J = _pseudo_inertia_by_definition(np.eye(10)).reshape(10, 16)
_J_TO_PI = _params_from_pseudo_inertia_by_definition(np.eye(16).reshape(16, 4, 4))


def _pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    return (pi @ _PI_TO_J).reshape(pi.shape[:-1] + (4, 4))


def _params_from_pseudo_inertia(j: np.ndarray) -> np.ndarray:
    return j.reshape(j.shape[:-2] + (16,)) @ _J_TO_PI


def params_to_pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    """Pseudo-inertia J (..., 4, 4) = [[0.5 tr(I_o) 1 - I_o, h], [h^T, m]] of pi (..., 10)."""
    return _pseudo_inertia(_as_array(pi, (10,), "pi"))


def pseudo_inertia_to_params(pseudo_inertia: np.ndarray) -> np.ndarray:
    """Standard parameters pi (..., 10) of a symmetric pseudo-inertia J (..., 4, 4)."""
    j = _as_array(pseudo_inertia, (4, 4), "pseudo_inertia")
    _check_symmetric(j, "pseudo_inertia")
    return _params_from_pseudo_inertia(j)


def principal_moments(inertia_com: np.ndarray) -> np.ndarray:
    """Principal moments (..., 3), sorted ascending, of a symmetric (..., 3, 3) inertia tensor."""
    inertia_com = _as_array(inertia_com, (3, 3), "inertia_com")
    _check_symmetric(inertia_com, "inertia_com")
    return np.linalg.eigvalsh(inertia_com)


# --------------------------------------------------------------------------- physical consistency


def _format_index(index: tuple[int, ...]) -> str:
    return f"at batch index {index}: " if index else ""


def physical_violation(pi: np.ndarray, tol: float = 0.0) -> str | None:
    """None if pi (..., 10) is physically consistent, else a message naming the failed condition.

    Checked in order: mass > tol, inertia about the centre of mass positive definite (smallest
    principal moment > tol), triangle inequality of the principal moments (I_1 + I_2 >= I_3 + tol),
    pseudo-inertia positive definite (smallest eigenvalue > tol). tol (>= 0, in the SI unit of each
    quantity) demands a margin; tol = 0 gives exactly the conditions above. For a batch
    the message is about the first inconsistent element (C order) and names its index.
    """
    pi = _as_array(pi, (10,), "pi")
    if not (np.isfinite(tol) and tol >= 0.0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol}")
    mass = pi[..., 0]
    mass_ok = mass > tol
    # Elements that fail the mass check are reported as such; a unit mass there only keeps the
    # centre of mass finite.
    safe_pi = pi.copy()
    safe_pi[..., 0] = np.where(mass > 0.0, mass, 1.0)
    moments = np.linalg.eigvalsh(_mass_com_inertia(safe_pi)[2])
    inertia_ok = moments[..., 0] > tol
    triangle_ok = moments[..., 0] + moments[..., 1] >= moments[..., 2] + tol
    j_min = np.linalg.eigvalsh(_pseudo_inertia(pi))[..., 0]
    j_ok = j_min > tol
    bad = ~(mass_ok & inertia_ok & triangle_ok & j_ok)
    if not bad.any():
        return None
    index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
    index = tuple(int(i) for i in index)
    where = _format_index(index)
    m = mass[index]
    i1, i2, i3 = (f"{x:.6g}" for x in moments[index])
    if not mass_ok[index]:
        return f"{where}mass must be positive (greater than {tol} kg), got {m:.6g} kg"
    if not inertia_ok[index]:
        return (
            f"{where}inertia about the centre of mass must be positive definite "
            f"(principal moments greater than {tol}), got principal moments {i1}, {i2}, {i3} kg m^2"
        )
    if not triangle_ok[index]:
        margin = f" + {tol}" if tol > 0.0 else ""
        return (
            f"{where}principal moments {i1}, {i2}, {i3} break the triangle inequality "
            f"{i1} + {i2} >= {i3}{margin}"
        )
    return (
        f"{where}pseudo-inertia must be positive definite (eigenvalues greater than {tol}), "
        f"got smallest eigenvalue {j_min[index]:.6g}"
    )


def project_physical(pi: np.ndarray, min_eig: float = 1e-9) -> np.ndarray:
    """Nearest (Frobenius, in pseudo-inertia) physically consistent body: J's eigenvalues are
    clipped at ``min_eig`` (scaled by the largest)."""
    j = params_to_pseudo_inertia(np.asarray(pi, dtype=float))
    lam, vec = np.linalg.eigh(j)
    floor = min_eig * max(float(lam.max()), 1e-12)
    return pseudo_inertia_to_params((vec * np.maximum(lam, floor)) @ vec.T)


def check_physical(pi: np.ndarray, tol: float = 0.0) -> None:
    """Raise ValueError with the message of physical_violation if pi is not consistent."""
    message = physical_violation(pi, tol)
    if message is not None:
        raise ValueError(f"pi is not physically consistent: {message}")


# --------------------------------------------------------------------------- log-Cholesky


def _w_from_eta(eta: np.ndarray) -> np.ndarray:
    w = np.empty(eta.shape)
    w[..., :3] = np.exp(eta[..., 1:4])
    w[..., 3:9] = eta[..., 4:10]
    w[..., 9] = 1.0
    return w


def log_cholesky_to_params(eta: np.ndarray) -> np.ndarray:
    """Standard parameters pi (..., 10) of log-Cholesky coordinates eta (..., 10), closed form."""
    eta = _as_array(eta, (10,), "eta")
    w = _w_from_eta(eta)
    return ((w[..., _PAIR_A] * w[..., _PAIR_B]) @ _PAIR_TO_PI) * np.exp(2.0 * eta[..., :1])


def params_to_log_cholesky(pi: np.ndarray) -> np.ndarray:
    """Log-Cholesky coordinates eta (..., 10) of pi (..., 10), via the upper Cholesky J = U U^T.

    Raises ValueError naming the violated condition if pi is not physically consistent.
    """
    pi = _as_array(pi, (10,), "pi")
    j = _pseudo_inertia(pi)
    try:
        # Upper Cholesky: U = P L P with L the lower Cholesky of P J P (P reverses the order).
        upper = np.linalg.cholesky(j[..., ::-1, ::-1])[..., ::-1, ::-1]
    except np.linalg.LinAlgError:
        message = physical_violation(pi) or "pseudo-inertia must be positive definite"
        raise ValueError(f"pi has no log-Cholesky coordinates: {message}") from None
    u44 = upper[..., 3:4, 3]
    eta = np.empty(pi.shape)
    eta[..., 0] = np.log(u44[..., 0])
    eta[..., 1:4] = np.log(np.diagonal(upper, axis1=-2, axis2=-1)[..., :3] / u44)
    eta[..., 4] = upper[..., 0, 1]
    eta[..., 5] = upper[..., 1, 2]
    eta[..., 6] = upper[..., 0, 2]
    eta[..., 7:10] = upper[..., :3, 3]
    eta[..., 4:10] /= u44
    return eta


def log_cholesky_jacobian(eta: np.ndarray) -> np.ndarray:
    """Analytic Jacobian D[..., i, j] = d pi_i / d eta_j of log_cholesky_to_params (..., 10, 10)."""
    eta = _as_array(eta, (10,), "eta")
    batch = eta.shape[:-1]
    w = _w_from_eta(eta)
    mass = np.exp(2.0 * eta[..., 0])
    q_w = (_Q_ROWS @ w[..., :, None]).reshape(batch + (10, 10))  # [k, a] = (Q[k] w)_a
    dw_deta = w[..., :9].copy()  # d e^d / dd = e^d; s and t enter w directly
    dw_deta[..., 3:] = 1.0
    jacobian = np.empty(batch + (10, 10))
    # Every pi entry is m times a function of eta[1:], and m = e^(2 alpha).
    jacobian[..., :, 0] = 2.0 * mass[..., None] * np.einsum("...ka,...a->...k", q_w, w)
    jacobian[..., :, 1:] = 2.0 * mass[..., None, None] * q_w[..., :, :9] * dw_deta[..., None, :]
    return jacobian


# --------------------------------------------------------------------------- frame changes


def pseudo_inertia_transform(
    pseudo_inertia: np.ndarray, rotation: np.ndarray, translation: np.ndarray
) -> np.ndarray:
    """J_B = T J_A T^T with T = [[R, p], [0, 1]], for frame A's pose x_B = R x_A + p in frame B.

    Leading shapes of pseudo_inertia (..., 4, 4), rotation (..., 3, 3) and translation (..., 3)
    broadcast together.
    """
    j = _as_array(pseudo_inertia, (4, 4), "pseudo_inertia")
    rotation = _as_array(rotation, (3, 3), "rotation")
    translation = _as_array(translation, (3,), "translation")
    _check_rotation(rotation)
    return _transform_pseudo_inertia(j, rotation, translation)


def _transform_pseudo_inertia(
    j: np.ndarray, rotation: np.ndarray, translation: np.ndarray
) -> np.ndarray:
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    t = np.zeros(batch + (4, 4))
    t[..., :3, :3] = rotation
    t[..., :3, 3] = translation
    t[..., 3, 3] = 1.0
    return t @ j @ np.swapaxes(t, -1, -2)


def transform_params(pi: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Express pi (..., 10), given in frame A, in frame B (about B's origin).

    rotation R (..., 3, 3) and translation p (..., 3), in metres, are frame A's pose in frame B:
    x_B = R x_A + p. Exact for any rigid change of frame (pseudo-inertia congruence).
    """
    pi = _as_array(pi, (10,), "pi")
    rotation = _as_array(rotation, (3, 3), "rotation")
    translation = _as_array(translation, (3,), "translation")
    _check_rotation(rotation)
    j_b = _transform_pseudo_inertia(_pseudo_inertia(pi), rotation, translation)
    return _params_from_pseudo_inertia(j_b)


# --------------------------------------------------------------------------- error metrics


def _positive_mass(pi: np.ndarray, name: str) -> None:
    if (pi[..., 0] <= 0.0).any():
        raise ValueError(f"{name} must have positive mass, got min mass {pi[..., 0].min()} kg")


def _checked_pair(pi_est: np.ndarray, pi_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both bodies as finite float arrays (..., 10) with positive masses, or ValueError."""
    pi_est = _as_array(pi_est, (10,), "pi_est")
    pi_true = _as_array(pi_true, (10,), "pi_true")
    _positive_mass(pi_est, "pi_est")
    _positive_mass(pi_true, "pi_true")
    return pi_est, pi_true


def mass_rel_error(pi_est: np.ndarray, pi_true: np.ndarray) -> np.ndarray:
    """Relative mass error |m_est - m_true| / m_true, shape (...)."""
    pi_est = _as_array(pi_est, (10,), "pi_est")
    pi_true = _as_array(pi_true, (10,), "pi_true")
    _positive_mass(pi_true, "pi_true")
    return np.abs(pi_est[..., 0] - pi_true[..., 0]) / pi_true[..., 0]


def com_error_m(pi_est: np.ndarray, pi_true: np.ndarray) -> np.ndarray:
    """Distance in metres between the estimated and true centres of mass, shape (...)
    (``estimate_errors``)."""
    return estimate_errors(*_checked_pair(pi_est, pi_true))[1]


def principal_rel_errors(pi_est: np.ndarray, pi_true: np.ndarray) -> np.ndarray:
    """|I_k,est - I_k,true| / I_k,true of the sorted principal moments about the com, (..., 3)
    (``estimate_errors``)."""
    return estimate_errors(*_checked_pair(pi_est, pi_true))[2]


def estimate_errors(
    pi_est: np.ndarray, pi_true: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`mass_rel_error`, `com_error_m` and `principal_rel_errors` of the same bodies, their
    inputs checked once: shapes (...), (...) and (..., 3). One compiled pass over the bodies."""
    pi_est = np.asarray(pi_est, dtype=float)
    pi_true = np.asarray(pi_true, dtype=float)
    for a, name in ((pi_est, "pi_est"), (pi_true, "pi_true")):
        if a.ndim < 1 or a.shape[-1] != 10:
            raise ValueError(f"{name} must have shape (..., 10), got shape {a.shape}")
    shape = np.broadcast_shapes(pi_est.shape, pi_true.shape)
    rows_est, rows_true = (
        (a if a.shape == shape else np.broadcast_to(a, shape)).reshape(-1, 10)
        for a in (pi_est, pi_true)
    )
    out = np.empty((rows_est.shape[0], 5))
    failed = _estimate_errors_kernel(rows_est, rows_true, out)
    if failed:
        _raise_invalid_pair(failed, pi_est, pi_true)
    out = out.reshape(shape[:-1] + (5,))
    return out[..., 0], out[..., 1], out[..., 2:]


def _raise_invalid_pair(failed: int, pi_est: np.ndarray, pi_true: np.ndarray) -> None:
    """The ValueError of `_checked_pair` (failed 1-4) or of a true body whose principal moments
    about its centre of mass are not all positive (5)."""
    if failed < 5:
        _checked_pair(pi_est, pi_true)
    raise ValueError("pi_true must have positive principal moments about its centre of mass")


@njit(cache=True)
def _estimate_errors_kernel(pi_est, pi_true, out):
    """Per body b (rows of (n, 10)): out[b] = [|m_e - m_t| / m_t, |c_e - c_t| (m),
    |I_k,e - I_k,t| / I_k,t for the principal moments about the com, ascending (3)].
    Returns 0, or the first failed check over all bodies: 1 pi_est not finite, 2 pi_true not
    finite, 3 a mass of pi_est not positive, 4 one of pi_true, 5 a true principal moment not
    positive."""
    checks = (
        np.isfinite(pi_est).all(),
        np.isfinite(pi_true).all(),
        (pi_est[:, 0] > 0.0).all(),
        (pi_true[:, 0] > 0.0).all(),
    )
    for k in range(4):
        if not checks[k]:
            return k + 1
    moments_true = _principal_moments_about_com(pi_true)
    if (moments_true <= 0.0).any():
        return 5
    return _errors_kernel(pi_est, pi_true, moments_true, out)


@njit(cache=True)
def _principal_moments_about_com(pi):
    """The principal moments about the com (n, 3), ascending, of bodies pi (n, 10) (kg m^2)."""
    moments = np.empty((pi.shape[0], 3))
    for b in range(pi.shape[0]):
        moments[b] = np.linalg.eigvalsh(_inertia_about_com(pi[b]))
    return moments


@njit(cache=True)
def _errors_kernel(pi_est, pi_true, moments_true, out):
    """`_estimate_errors_kernel` given the true principal moments (n, 3); returns 0, 1 or 3."""
    if not np.isfinite(pi_est).all():
        return 1
    if not (pi_est[:, 0] > 0.0).all():
        return 3
    for b in range(pi_est.shape[0]):
        m_est, m_true = pi_est[b, 0], pi_true[b, 0]
        out[b, 0] = np.abs(m_est - m_true) / m_true
        dc = pi_est[b, 1:4] / m_est - pi_true[b, 1:4] / m_true
        out[b, 1] = np.sqrt(dc[0] * dc[0] + dc[1] * dc[1] + dc[2] * dc[2])
        moments_est = np.linalg.eigvalsh(_inertia_about_com(pi_est[b]))
        out[b, 2:] = np.abs(moments_est - moments_true[b]) / moments_true[b]
    return 0


def true_principal_moments(pi_true: np.ndarray) -> np.ndarray:
    """Principal moments about the com (n, 3) of true bodies (n, 10), checked (ValueError)."""
    pi_true = np.ascontiguousarray(pi_true, dtype=float).reshape(-1, 10)
    estimate_errors(pi_true, pi_true)
    return _principal_moments_about_com(pi_true)


def errors_given_true(pi_est, pi_true, moments_true, out) -> None:
    """``estimate_errors`` of float rows (n, 10) into out (n, 5), the true principal moments
    (n, 3) known (``true_principal_moments``): no shape checks; the same ValueError."""
    if _errors_kernel(pi_est, pi_true, moments_true, out):
        estimate_errors(pi_est, pi_true)  # raises the ValueError of that estimate


@njit(cache=True)
def _inertia_about_com(pi):
    """Parallel axis: I_c = I_o - (|h|^2 1 - h h^T) / m (3, 3), h = m c, of one body pi (10,)."""
    h = pi[1:4]
    hh = h[0] * h[0] + h[1] * h[1] + h[2] * h[2]
    inertia = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            shift = (hh if r == c else 0.0) - h[r] * h[c]
            inertia[r, c] = pi[4 + _TENSOR_TO_VEC[3 * r + c]] - shift / pi[0]
    return inertia


def pseudo_inertia_distance(pi_a: np.ndarray, pi_b: np.ndarray) -> np.ndarray:
    """Riemannian distance sqrt(sum_i log(lambda_i)^2) between two bodies, shape (...).

    lambda are the generalised eigenvalues of (J_b, J_a) (Lee and Park 2018). The distance does
    not depend on the frame both are expressed in. Both bodies must be physically consistent.
    """
    pi_a = _as_array(pi_a, (10,), "pi_a")
    pi_b = _as_array(pi_b, (10,), "pi_b")
    j_a, j_b = np.broadcast_arrays(_pseudo_inertia(pi_a), _pseudo_inertia(pi_b))
    try:
        lower_a = np.linalg.cholesky(j_a)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"pi_a must be physically consistent: {physical_violation(pi_a)}"
        ) from None
    # L^-1 J_b L^-T has the generalised eigenvalues of (J_b, J_a).
    half = np.linalg.solve(lower_a, j_b)
    whitened = np.linalg.solve(lower_a, np.swapaxes(half, -1, -2))
    eigenvalues = np.linalg.eigvalsh(0.5 * (whitened + np.swapaxes(whitened, -1, -2)))
    if (eigenvalues <= 0.0).any():
        raise ValueError(f"pi_b must be physically consistent: {physical_violation(pi_b)}")
    return np.sqrt(np.sum(np.log(eigenvalues) ** 2, axis=-1))


# --------------------------------------------------------------------------- value object


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class InertialParams:
    """One physically consistent rigid body: mass (kg), com (m) and inertia about the com (kg m^2).

    com and inertia_com are expressed in the body frame the parameters refer to; they are stored
    as read-only float copies. Construction raises ValueError for a wrong shape, a non-finite
    entry or a physically inconsistent body.
    """

    mass: float
    com: np.ndarray
    inertia_com: np.ndarray

    def __post_init__(self) -> None:
        if np.ndim(self.mass) != 0:
            raise ValueError(f"mass must be a scalar, got shape {np.shape(self.mass)}")
        mass = _as_single(self.mass, (), "mass")
        com = _as_single(self.com, (3,), "com")
        inertia_com = _as_single(self.inertia_com, (3, 3), "inertia_com")
        _check_symmetric(inertia_com, "inertia_com")
        object.__setattr__(self, "mass", float(mass))
        object.__setattr__(self, "com", _read_only(com))
        object.__setattr__(self, "inertia_com", _read_only(inertia_com))
        check_physical(self.to_vector())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, InertialParams):
            return NotImplemented
        return (
            self.mass == other.mass
            and np.array_equal(self.com, other.com)
            and np.array_equal(self.inertia_com, other.inertia_com)
        )

    def __hash__(self) -> int:
        return hash((self.mass, self.com.tobytes(), self.inertia_com.tobytes()))

    def to_vector(self) -> np.ndarray:
        """Standard parameter vector pi (10,) about the frame origin."""
        return params_from_mass_com_inertia(self.mass, self.com, self.inertia_com)

    @classmethod
    def from_vector(cls, pi: np.ndarray) -> InertialParams:
        """Body of a standard parameter vector pi (10,)."""
        pi = _as_single(pi, (10,), "pi")
        check_physical(pi)
        mass, com, inertia_com = _mass_com_inertia(pi)
        return cls(float(mass), com, 0.5 * (inertia_com + inertia_com.T))

    def pseudo_inertia(self) -> np.ndarray:
        """Pseudo-inertia J (4, 4) about the frame origin."""
        return _pseudo_inertia(self.to_vector())

    def to_log_cholesky(self) -> np.ndarray:
        """Log-Cholesky coordinates eta (10,)."""
        return params_to_log_cholesky(self.to_vector())

    @classmethod
    def from_log_cholesky(cls, eta: np.ndarray) -> InertialParams:
        """Body of log-Cholesky coordinates eta (10,)."""
        eta = _as_single(eta, (10,), "eta")
        return cls.from_vector(log_cholesky_to_params(eta))

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> InertialParams:
        """The same body expressed in frame B, where x_B = rotation @ x_A + translation (m)."""
        rotation = _as_single(rotation, (3, 3), "rotation")
        translation = _as_single(translation, (3,), "translation")
        _check_rotation(rotation)
        inertia_com = rotation @ self.inertia_com @ rotation.T
        return InertialParams(
            self.mass, rotation @ self.com + translation, 0.5 * (inertia_com + inertia_com.T)
        )

    def principal_moments(self) -> np.ndarray:
        """Principal moments of inertia about the com (3,), sorted ascending, kg m^2."""
        return np.linalg.eigvalsh(self.inertia_com)
