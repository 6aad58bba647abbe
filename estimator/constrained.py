"""Physically consistent estimates: the body of highest posterior density under N(mean, cov).

Parameters and frames: pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m,
kg m^2) in one body-fixed frame with origin o, h = m c (c the centre of mass from o), I the
inertia about o. The pseudo-inertia J(pi) = [[0.5 tr(I) 1 - I, h], [h^T, m]] (4 x 4) is linear in
pi, J(pi) = sum_k pi_k E_k, and a body is physically realisable exactly when J is positive
definite (``estimator.inertia``).

The problem solved by `constrained_mode`, with cov = L L^T and pi = mean + L v (whitened v):

    minimise  0.5 |v|^2  (half the squared Mahalanobis distance of pi from the mean)
    subject to  J(mean + L v) positive definite.

The constraint set is convex and J is linear in v, J(v) = J(mean) + sum_l v_l B_l with
B_l = sum_k L_kl E_k, so this is a small semidefinite program. It is solved by a log-det barrier
method: for a decreasing weight t, minimise

    f_t(v) = 0.5 |v|^2 - t log det J(v)

by Newton's method. With A_l = J^-1 B_l the barrier's derivatives are

    d/dv_l log det J = tr(A_l),    d2/dv_l dv_m log det J = -tr(A_l A_m),

so the Newton step u solves (I + t H) u = -(v - t g) with g_l = tr(A_l), H_lm = tr(A_l A_m). With
J's Cholesky factor J = C C^T, A_l is similar to the symmetric M_l = C^-1 B_l C^-T, so g_l =
tr(M_l) and H_lm = tr(M_l M_m) = sum_ab M_l[a, b] M_m[a, b] (B_l = J(L e_l), J being linear). The
step is backtracked (halved) until J stays positive definite and f_t decreases by at least a
quarter of the predicted decrease (Armijo); Newton stops once the decrement
lambda^2 = -(gradient . u) falls below gap / 10. The barrier's bound on the remaining excess of
0.5 |v|^2 is 4 t for a 4 x 4 J, so t is divided by 50 from 1 (or 1e-2 from a warm start) down to
gap / 4. Where the iterate stops depends on the path, so the path is part of the result.

Every kernel here is compiled with numba (``@njit(cache=True)``); the Newton loop works in arrays
made once per call. `constrained_mode` tests the mean's consistency in one compiled call; for an
inconsistent mean three more follow: the start (clipping, cov's Cholesky, the warm start),
`barrier_newton`, the result. `cholesky_lower` and `solve_lower` are the small factorisation
kernels the UKF (``estimator.unscented``) shares.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .checks import all_finite

__all__ = ["cholesky_lower", "constrained_mode", "is_physical", "solve_lower"]

N_PARAMS = 10

# Barrier weight schedule and stopping rules (see the module docstring).
_T_START = 1.0
_T_WARM_START = 1e-2
_T_DIVISOR = 50.0
_MAX_NEWTON_STEPS = 50
_MIN_STEP_SCALE = 1e-12
_ARMIJO_FRACTION = 0.25
_CLIP_MIN_EIG = 1e-3


# --------------------------------------------------------------------------- small kernels


@njit(cache=True)
def _cholesky_into(a: np.ndarray, lower: np.ndarray) -> bool:
    """Lower Cholesky factor L of a symmetric a (n, n) (reads its lower triangle), a = L L^T,
    written into the lower triangle of ``lower`` (n, n); whether a is positive definite with
    finite pivots (L is partial when not). The entries above the diagonal are not written."""
    n = a.shape[0]
    for j in range(n):
        pivot = a[j, j]
        for k in range(j):
            pivot -= lower[j, k] * lower[j, k]
        if not 0.0 < pivot < math.inf:  # also false for NaN
            return False
        lower[j, j] = math.sqrt(pivot)
        for i in range(j + 1, n):
            entry = a[i, j]
            for k in range(j):
                entry -= lower[i, k] * lower[j, k]
            lower[i, j] = entry / lower[j, j]
    return True


@njit(cache=True)
def cholesky_lower(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """Lower Cholesky factor L of a symmetric matrix (reads its lower triangle), a = L L^T, and
    whether a is positive definite with finite pivots (L is partial when not)."""
    lower = np.zeros(a.shape)
    return lower, _cholesky_into(a, lower)


@njit(cache=True)
def solve_lower(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """L^-1 rhs for a lower-triangular L (n, n) and rhs (n, k), by forward substitution."""
    n, k = rhs.shape
    out = np.empty((n, k))
    for i in range(n):
        for c in range(k):
            entry = rhs[i, c]
            for j in range(i):
                entry -= lower[i, j] * out[j, c]
            out[i, c] = entry / lower[i, i]
    return out


@njit(cache=True)
def _cholesky_solve_into(lower: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> None:
    """a^-1 rhs into out (n,), from the Cholesky factor L of a (a = L L^T): L y = rhs by forward,
    then L^T out = y by back substitution."""
    n = rhs.size
    for i in range(n):
        entry = rhs[i]
        for j in range(i):
            entry -= lower[i, j] * out[j]
        out[i] = entry / lower[i, i]
    for i in range(n - 1, -1, -1):
        entry = out[i]
        for j in range(i + 1, n):
            entry -= lower[j, i] * out[j]
        out[i] = entry / lower[i, i]


@njit(cache=True)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    total = 0.0
    for i in range(a.size):
        total += a[i] * b[i]
    return total


@njit(cache=True)
def _pseudo_inertia_into(pi: np.ndarray, j: np.ndarray) -> None:
    """J(pi) = [[0.5 tr(I) 1 - I, h], [h^T, m]] (4, 4) into j, for pi = [m, h, I_xx, I_yy, I_zz,
    I_xy, I_xz, I_yz] and I = [[I_xx, I_xy, I_xz], [I_xy, I_yy, I_yz], [I_xz, I_yz, I_zz]]."""
    half_trace = 0.5 * (pi[4] + pi[5] + pi[6])
    for a in range(3):
        j[a, a] = half_trace - pi[4 + a]
        j[a, 3] = j[3, a] = pi[1 + a]
    j[0, 1] = j[1, 0] = -pi[7]
    j[0, 2] = j[2, 0] = -pi[8]
    j[1, 2] = j[2, 1] = -pi[9]
    j[3, 3] = pi[0]


@njit(cache=True)
def _params_into(j: np.ndarray, pi: np.ndarray) -> None:
    """pi of a symmetric pseudo-inertia J into pi (10,): m = J_33, h = J[:3, 3] and
    I = tr(S) 1 - S for S = J[:3, :3] (its upper triangle)."""
    trace = j[0, 0] + j[1, 1] + j[2, 2]
    pi[0] = j[3, 3]
    for a in range(3):
        pi[1 + a] = j[a, 3]
        pi[4 + a] = trace - j[a, a]
    pi[7], pi[8], pi[9] = -j[0, 1], -j[0, 2], -j[1, 2]


@njit(cache=True)
def _body_into(mean: np.ndarray, lower: np.ndarray, v: np.ndarray, pi: np.ndarray) -> None:
    """The body of whitened coordinates v: pi = mean + L v, for a lower-triangular L."""
    for i in range(mean.size):
        entry = 0.0
        for k in range(i + 1):
            entry += lower[i, k] * v[k]
        pi[i] = mean[i] + entry


@njit(cache=True)
def _is_physical(pi: np.ndarray) -> bool:
    """Whether J(pi) is positive definite (its Cholesky succeeds)."""
    j = np.empty((4, 4))
    _pseudo_inertia_into(pi, j)
    return _cholesky_into(j, np.empty((4, 4)))


@njit(cache=True)
def _log_det_if_definite(j: np.ndarray, chol: np.ndarray) -> tuple[float, bool]:
    """log det J = 2 sum log diag(C) with J = C C^T (C into chol), and whether J is positive
    definite."""
    if not _cholesky_into(j, chol):
        return 0.0, False
    total = 0.0
    for i in range(4):
        total += math.log(chol[i, i])
    return 2.0 * total, True


@njit(cache=True)
def _clipped_body(pi: np.ndarray, min_eig: float) -> np.ndarray:
    """``inertia.project_physical`` of one body: J(pi)'s eigenvalues clipped at ``min_eig``
    times the largest (at least 1e-12), J = V diag(max(lambda, floor)) V^T."""
    j = np.empty((4, 4))
    _pseudo_inertia_into(pi, j)
    lam, vec = np.linalg.eigh(j)
    floor = min_eig * max(lam.max(), 1e-12)
    clipped = np.empty(N_PARAMS)
    _params_into((vec * np.maximum(lam, floor)) @ vec.T, clipped)
    return clipped


# --------------------------------------------------------------------------- the barrier method


@njit(cache=True)
def _lower_inverse_into(lower: np.ndarray, inverse: np.ndarray) -> None:
    """W = L^-1 of a lower-triangular L (n, n) into the lower triangle of ``inverse``, by forward
    substitution on the identity's columns."""
    n = lower.shape[0]
    for c in range(n):
        for i in range(c, n):
            entry = 1.0 if i == c else 0.0
            for k in range(c, i):
                entry -= lower[i, k] * inverse[k, c]
            inverse[i, c] = entry / lower[i, i]


@njit(cache=True)
def _congruence_into(w: np.ndarray, b: np.ndarray, half: np.ndarray, packed: np.ndarray) -> None:
    """The upper triangle of M = W B W^T for a lower-triangular W and a symmetric B (4, 4), row by
    row into packed (10,) (M_00, M_01, M_02, M_03, M_11, ...): half = B W^T (the entries c <= a
    that M's upper triangle reads), then M_ab = sum_c W_ac half_cb."""
    for a in range(4):
        for c in range(a + 1):
            entry = 0.0
            for d in range(a + 1):
                entry += b[c, d] * w[a, d]
            half[c, a] = entry
    q = 0
    for a in range(4):
        for col in range(a, 4):
            entry = 0.0
            for c in range(a + 1):
                entry += w[a, c] * half[c, col]
            packed[q] = entry
            q += 1


# The packed upper triangle's diagonal entries, and the weights that make the dot product of two
# packed symmetric matrices their Frobenius product sum_ab M_ab N_ab.
_PACKED_DIAGONAL = np.array([0, 4, 7, 9])
_PACKED_WEIGHTS = np.array([1.0, 2.0, 2.0, 2.0, 1.0, 2.0, 2.0, 1.0, 2.0, 1.0])


@njit(cache=True)
def _barrier_derivatives(chol_j, j_derivs, inverse, half, packed, grad, hess) -> None:
    """Gradient g_l = tr(A_l) and (minus) Hessian H_lm = tr(A_l A_m) of log det J in v, into
    grad (n,) and hess (n, n), with A_l = J^-1 B_l and B_l = j_derivs[l] = dJ/dv_l. With
    J = C C^T (``chol_j``) and W = C^-1, A_l = C^-T M_l C^T for the symmetric M_l = W B_l W^T
    (its upper triangle into packed[l]), so g_l = tr(M_l) and
    H_lm = tr(M_l M_m) = sum_ab M_l[a, b] M_m[a, b]."""
    _lower_inverse_into(chol_j, inverse)
    n = j_derivs.shape[0]
    for k in range(n):
        _congruence_into(inverse, j_derivs[k], half, packed[k])
        grad[k] = 0.0
        for q in _PACKED_DIAGONAL:
            grad[k] += packed[k, q]
    for k in range(n):
        for m in range(k + 1):
            entry = 0.0
            for q in range(_PACKED_WEIGHTS.size):
                entry += _PACKED_WEIGHTS[q] * packed[k, q] * packed[m, q]
            hess[k, m] = hess[m, k] = entry


@njit(cache=True)
def _newton_step(v, t, grad_b, hess_b, gradient, system, chol, step) -> tuple[float, bool]:
    """Newton direction u of f_t at v into ``step``: (I + t H) u = -gradient with
    gradient = v - t g (into ``gradient``). Returns the decrement -(gradient . u) and ok, False if
    the system's Cholesky fails (it is positive definite in exact arithmetic)."""
    n = v.size
    for k in range(n):
        gradient[k] = v[k] - t * grad_b[k]
        for m in range(k + 1):
            system[k, m] = t * hess_b[k, m]
        system[k, k] += 1.0
    if not _cholesky_into(system, chol):
        return 0.0, False
    _cholesky_solve_into(chol, gradient, step)
    for k in range(n):
        step[k] = -step[k]
    return -_dot(gradient, step), True


@njit(cache=True)
def _backtrack(mean, lower, v, step, t, decrement, log_det, trial, pi, j, chol):
    """Armijo backtracking from v along u = ``step``: the first scale 1, 1/2, 1/4, ... above
    1e-12 at which J(mean + L (v + scale u)) is positive definite and f_t falls by at least a
    quarter of scale x decrement. Leaves that point in ``trial`` (its J's Cholesky in ``chol``)
    and returns (scale, log det J there); scale 0.0 if there is none."""
    value = 0.5 * _dot(v, v) - t * log_det
    scale = 1.0
    while scale > _MIN_STEP_SCALE:
        for i in range(v.size):
            trial[i] = v[i] + scale * step[i]
        _body_into(mean, lower, trial, pi)
        _pseudo_inertia_into(pi, j)
        trial_log_det, definite = _log_det_if_definite(j, chol)
        trial_value = 0.5 * _dot(trial, trial) - t * trial_log_det
        if definite and trial_value <= value - _ARMIJO_FRACTION * scale * decrement:
            return scale, trial_log_det
        scale *= 0.5
    return 0.0, 0.0


@njit(cache=True)
def barrier_newton(
    mean: np.ndarray, lower: np.ndarray, v: np.ndarray, t: float, gap: float
) -> tuple[np.ndarray, bool]:
    """Minimise 0.5 |v|^2 over J(mean + L v) positive definite by the barrier method of the
    module docstring, from a strictly feasible v at weight t. Returns v (a new array) and whether
    the iteration ran without numerical breakdown."""
    n = v.size
    j_derivs = np.empty((n, 4, 4))  # B_l = dJ/dv_l = J(L e_l), J being linear
    for k in range(n):
        _pseudo_inertia_into(lower[:, k], j_derivs[k])
    v, trial, pi, step, gradient = v.copy(), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    grad_b, hess_b, packed = np.empty(n), np.empty((n, n)), np.empty((n, 10))
    system, system_chol = np.empty((n, n)), np.empty((n, n))
    j, chol_j, trial_chol = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    inverse, half = np.empty((4, 4)), np.empty((4, 4))
    _body_into(mean, lower, v, pi)
    _pseudo_inertia_into(pi, j)
    log_det, definite = _log_det_if_definite(j, chol_j)
    if not definite:
        return v, False
    _barrier_derivatives(chol_j, j_derivs, inverse, half, packed, grad_b, hess_b)
    while True:
        for _ in range(_MAX_NEWTON_STEPS):
            decrement, ok = _newton_step(v, t, grad_b, hess_b, gradient, system, system_chol, step)
            if not (ok and math.isfinite(decrement)):
                return v, False
            if decrement < 0.1 * gap:
                break
            scale, trial_log_det = _backtrack(
                mean, lower, v, step, t, decrement, log_det, trial, pi, j, trial_chol
            )
            if scale == 0.0:
                break
            v[:] = trial
            log_det = trial_log_det
            chol_j, trial_chol = trial_chol, chol_j
            _barrier_derivatives(chol_j, j_derivs, inverse, half, packed, grad_b, hess_b)
        if 4.0 * t <= gap:
            return v, True
        t = max(t / _T_DIVISOR, 0.25 * gap)


# --------------------------------------------------------------------------- the mode


@njit(cache=True)
def _whitened(mean: np.ndarray, lower: np.ndarray, pi: np.ndarray) -> np.ndarray:
    """v = L^-1 (pi - mean)."""
    return solve_lower(lower, (pi - mean).reshape(-1, 1))[:, 0]


@njit(cache=True)
def _barrier_setup(mean, cov, start, use_start):
    """Where the barrier method starts for an inconsistent mean: (clipped, L, v, t, definite), with
    ``clipped`` the eigenvalue-clipped body. ``definite`` False: cov is not positive definite (no
    L, v). Else cov = L L^T and v = L^-1 (clipped - mean) at t = 1, or ``start``'s at t = 1e-2 if
    ``use_start`` and start is a finite consistent body nearer the mean."""
    clipped, lower = _clipped_body(mean, _CLIP_MIN_EIG), np.zeros((N_PARAMS, N_PARAMS))
    if not _cholesky_into(cov, lower):
        return clipped, lower, clipped, 0.0, False
    v = _whitened(mean, lower, clipped)
    if use_start and all_finite(start) and _is_physical(start):
        v_start = _whitened(mean, lower, start)
        if _dot(v_start, v_start) < _dot(v, v):
            return clipped, lower, v_start, _T_WARM_START, True
    return clipped, lower, v, _T_START, True


@njit(cache=True)
def _barrier_result(mean, lower, v, solved, clipped) -> tuple[np.ndarray, bool]:
    """(mean + L v, True) if the iteration solved and that body is consistent, else
    (clipped, False)."""
    pi = np.empty(N_PARAMS)
    _body_into(mean, lower, v, pi)
    if solved and _is_physical(pi):
        return pi, True
    return clipped, False


def _check_body(pi: np.ndarray) -> None:
    if pi.shape != (N_PARAMS,) or not all_finite(pi):
        raise ValueError(f"pi must be a finite array of shape ({N_PARAMS},), got {pi}")


def is_physical(pi: np.ndarray) -> bool:
    """Whether pi (10,) is a realisable body: J(pi) positive definite (its Cholesky succeeds).
    A ValueError if pi is not a finite (10,) array."""
    pi = np.ascontiguousarray(pi, dtype=float)
    _check_body(pi)
    return _is_physical(pi)


def constrained_mode(
    mean: np.ndarray,
    cov: np.ndarray,
    start: np.ndarray | None = None,
    gap: float = 1e-4,
) -> tuple[np.ndarray, bool]:
    """The physically consistent body of highest density under N(mean, cov): (pi, solved).

    Minimises the Mahalanobis distance of pi from ``mean`` over bodies with a positive definite
    pseudo-inertia, by the barrier method of the module docstring (``gap`` bounds the remaining
    excess of the half squared distance). It starts from the eigenvalue-clipped pseudo-inertia
    of ``mean`` or from ``start`` (a consistent body, such as the previous mode of a filter whose
    state moved a little), whichever is nearer. A consistent ``mean`` is its own mode (returned
    as a copy). The result is always strictly consistent: should the iteration break down (a
    covariance that is not positive definite, rounding next to the boundary), it returns the
    eigenvalue-clipped body with ``solved`` False.
    """
    mean = np.ascontiguousarray(mean, dtype=float)
    if not gap > 0.0:
        raise ValueError(f"gap must be positive, got {gap}")
    if mean.shape == (N_PARAMS,) and _is_physical(mean):  # False for a NaN or infinite entry
        return mean.copy(), True
    _check_body(mean)
    cov = np.ascontiguousarray(cov, dtype=float)
    if cov.shape != (N_PARAMS, N_PARAMS):
        raise ValueError(f"cov must have shape ({N_PARAMS}, {N_PARAMS}), got {cov.shape}")
    use_start = start is not None and np.shape(start) == (N_PARAMS,)
    start = np.ascontiguousarray(start, dtype=float) if use_start else mean
    clipped, lower, v, t, definite = _barrier_setup(mean, cov, start, use_start)
    if not definite:
        return clipped, False
    v, solved = barrier_newton(mean, lower, v, t, gap)
    return _barrier_result(mean, lower, v, solved, clipped)
