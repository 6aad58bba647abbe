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

so the Newton step u solves (I + t H) u = -(v - t g) with g_l = tr(A_l), H_lm = tr(A_l A_m). The
step is backtracked (halved) until J stays positive definite and f_t decreases by at least a
quarter of the predicted decrease (Armijo); Newton stops once the decrement
lambda^2 = -(gradient . u) falls below gap / 10. The barrier's bound on the remaining excess of
0.5 |v|^2 is 4 t for a 4 x 4 J, so t is divided by 50 from 1 (or 1e-2 from a warm start) down to
gap / 4. Where the iterate stops depends on the path, so the path is part of the result.

Every kernel here is compiled with numba (``@njit(cache=True)``); `cholesky_lower` and
`solve_lower` are the small factorisation kernels the UKF (``estimator.unscented``) shares.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .inertia import params_to_pseudo_inertia, project_physical

__all__ = ["cholesky_lower", "cholesky_solve", "constrained_mode", "is_physical", "solve_lower"]

N_PARAMS = 10

# J(pi) = pi @ PSEUDO_INERTIA_BASIS reshaped to (4, 4): row k is E_k = J(e_k), flattened.
PSEUDO_INERTIA_BASIS = np.ascontiguousarray(
    params_to_pseudo_inertia(np.eye(N_PARAMS)).reshape(-1, 16)
)

# Barrier weight schedule and stopping rules (see the module docstring).
_T_START = 1.0
_T_WARM_START = 1e-2
_T_DIVISOR = 50.0
_MAX_NEWTON_STEPS = 50
_MIN_STEP_SCALE = 1e-12
_ARMIJO_FRACTION = 0.25
_CLIP_MIN_EIG = 1e-3


@njit(cache=True)
def cholesky_lower(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """Lower Cholesky factor L of a symmetric matrix (reads its lower triangle), a = L L^T, and
    whether a is positive definite with finite pivots (L is partial when not)."""
    n = a.shape[0]
    lower = np.zeros((n, n))
    for j in range(n):
        pivot = a[j, j]
        for k in range(j):
            pivot -= lower[j, k] * lower[j, k]
        if not 0.0 < pivot < math.inf:  # also false for NaN
            return lower, False
        lower[j, j] = math.sqrt(pivot)
        for i in range(j + 1, n):
            entry = a[i, j]
            for k in range(j):
                entry -= lower[i, k] * lower[j, k]
            lower[i, j] = entry / lower[j, j]
    return lower, True


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
def solve_upper_transposed(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """L^-T rhs for a lower-triangular L (n, n) and rhs (n, k), by back substitution."""
    n, k = rhs.shape
    out = np.empty((n, k))
    for i in range(n - 1, -1, -1):
        for c in range(k):
            entry = rhs[i, c]
            for j in range(i + 1, n):
                entry -= lower[j, i] * out[j, c]
            out[i, c] = entry / lower[i, i]
    return out


@njit(cache=True)
def cholesky_solve(lower: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """a^-1 rhs from the Cholesky factor L of a (a = L L^T), rhs (n, k)."""
    return solve_upper_transposed(lower, solve_lower(lower, rhs))


@njit(cache=True)
def _log_det_if_definite(j: np.ndarray) -> tuple[float, bool]:
    """log det J = 2 sum log diag(L_J), and whether J is positive definite."""
    lower, definite = cholesky_lower(j)
    if not definite:
        return 0.0, False
    return 2.0 * np.log(np.diag(lower)).sum(), True


@njit(cache=True)
def _barrier_derivatives(j: np.ndarray, j_derivs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient g_l = tr(A_l) and (minus) Hessian H_lm = tr(A_l A_m) of log det J in v, with
    A_l = J^-1 B_l and B_l = j_derivs[l] = dJ/dv_l."""
    n = j_derivs.shape[0]
    lower, _ = cholesky_lower(j)
    j_inv = cholesky_solve(lower, np.eye(4))
    a = np.empty_like(j_derivs)
    a_transposed = np.empty_like(j_derivs)
    grad = np.empty(n)
    for k in range(n):
        a[k] = j_inv @ j_derivs[k]
        a_transposed[k] = a[k].T
        grad[k] = np.trace(a[k])
    # tr(A_l A_m) = vec(A_l) . vec(A_m^T)
    hess = a.reshape(n, 16) @ a_transposed.reshape(n, 16).T
    return grad, hess


@njit(cache=True)
def _pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    """J(pi) (4, 4) = sum_k pi_k E_k."""
    return (pi @ PSEUDO_INERTIA_BASIS).reshape(4, 4)


@njit(cache=True)
def _newton_step(v: np.ndarray, t: float, grad_b: np.ndarray, hess_b: np.ndarray):
    """Newton direction u of f_t at v and the decrement -(gradient . u); ok False if the
    system's Cholesky fails (positive definite in exact arithmetic)."""
    grad = v - t * grad_b
    system = np.eye(v.size) + t * hess_b
    lower, ok = cholesky_lower(system)
    if not ok:
        return grad, 0.0, False
    step = -cholesky_solve(lower, grad.reshape(-1, 1)).ravel()
    return step, -(grad @ step), True


@njit(cache=True)
def barrier_newton(
    mean: np.ndarray, lower: np.ndarray, v: np.ndarray, t: float, gap: float
) -> tuple[np.ndarray, bool]:
    """Minimise 0.5 |v|^2 over J(mean + L v) positive definite by the barrier method of the
    module docstring, from a strictly feasible v at weight t. Returns v and whether the
    iteration ran without numerical breakdown."""
    j_derivs = (lower.T @ PSEUDO_INERTIA_BASIS).reshape(-1, 4, 4)  # B_l = sum_k L_kl E_k
    j = _pseudo_inertia(mean + lower @ v)
    log_det, definite = _log_det_if_definite(j)
    if not definite:
        return v, False
    grad_b, hess_b = _barrier_derivatives(j, j_derivs)
    while True:
        for _ in range(_MAX_NEWTON_STEPS):
            step, decrement, ok = _newton_step(v, t, grad_b, hess_b)
            if not (ok and math.isfinite(decrement)):
                return v, False
            if decrement < 0.1 * gap:
                break
            value = 0.5 * (v @ v) - t * log_det
            scale = 1.0
            accepted = False
            while scale > _MIN_STEP_SCALE:
                trial = v + scale * step
                trial_j = _pseudo_inertia(mean + lower @ trial)
                trial_log_det, definite = _log_det_if_definite(trial_j)
                trial_value = 0.5 * (trial @ trial) - t * trial_log_det
                if definite and trial_value <= value - _ARMIJO_FRACTION * scale * decrement:
                    accepted = True
                    break
                scale *= 0.5
            if not accepted:
                break
            v, log_det = trial, trial_log_det
            grad_b, hess_b = _barrier_derivatives(trial_j, j_derivs)
        if 4.0 * t <= gap:
            return v, True
        t = max(t / _T_DIVISOR, 0.25 * gap)


@njit(cache=True)
def _is_physical(pi: np.ndarray) -> bool:
    return cholesky_lower(_pseudo_inertia(pi))[1]


def is_physical(pi: np.ndarray) -> bool:
    """Whether pi (10,) is a realisable body: J(pi) positive definite (its Cholesky succeeds).
    A ValueError if pi is not a finite (10,) array."""
    pi = np.asarray(pi, dtype=float)
    if pi.shape != (N_PARAMS,) or not np.isfinite(pi).all():
        raise ValueError(f"pi must be a finite array of shape ({N_PARAMS},), got {pi}")
    return _is_physical(np.ascontiguousarray(pi))


def _barrier_start(
    mean: np.ndarray, lower: np.ndarray, clipped: np.ndarray, start: np.ndarray | None
) -> tuple[np.ndarray, float]:
    """Whitened starting point v and barrier weight t: the eigenvalue-clipped body at t = 1, or
    ``start`` further down the central path (t = 1e-2) if it is consistent and nearer the mean."""
    v = solve_lower(lower, (clipped - mean).reshape(-1, 1))[:, 0]
    if start is not None:
        start = np.asarray(start, dtype=float)
        if start.shape == (N_PARAMS,) and np.isfinite(start).all() and _is_physical(start):
            v_start = solve_lower(lower, (start - mean).reshape(-1, 1))[:, 0]
            if v_start @ v_start < v @ v:
                return v_start, _T_WARM_START
    return v, _T_START


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
    if is_physical(mean):
        return mean.copy(), True
    clipped = project_physical(mean, min_eig=_CLIP_MIN_EIG)
    cov = np.ascontiguousarray(cov, dtype=float)
    if cov.shape != (N_PARAMS, N_PARAMS):
        raise ValueError(f"cov must have shape ({N_PARAMS}, {N_PARAMS}), got {cov.shape}")
    lower, definite = cholesky_lower(cov)
    if not definite:
        return clipped, False
    v, t = _barrier_start(mean, lower, clipped, start)
    v, solved = barrier_newton(mean, lower, v, t, gap)
    pi = mean + lower @ v
    if solved and _is_physical(pi):
        return pi, True
    return clipped, False
