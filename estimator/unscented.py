"""Compiled pieces of the unscented Kalman filter of ``estimator.ukf``, one per step of filterpy's
UKF: Merwe sigma points -> unscented transform (and cross-covariance) -> gain and posterior.

The equations are those of the ``estimator.ukf`` docstring. Every kernel is compiled with numba
(``@njit(cache=True)``). A filter keeps its arrays in one flat float64 buffer (`filter_arrays`
gives the views), so that an update is one call that passes a handful of arrays and updates the
filter in place; the kernels called from Python are compiled for C-contiguous float64 arrays
when this module is imported (or loaded from numba's cache) and raise TypeError for anything
else, which the filters convert. The products are numba's ``@`` (BLAS); the elementwise steps
around them are loops that write their result once, as numba's array expressions allocate a
temporary per operation, which for arrays this small costs more than the arithmetic.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit, types

from .checks import all_finite
from .constrained import cholesky_lower, solve_lower

__all__ = [
    "cross_covariance",
    "draw_merwe_sigma_points",
    "filter_arrays",
    "merwe_sigma_points",
    "state_size",
    "unscented_transform",
    "unscented_update",
]

# Outcomes of an update. `BAD_SHAPE` is raised as a ValueError by the filters.
OK, BAD_R, BAD_P, BAD_H, BAD_S, BAD_Z, BAD_NIS, GATED, BAD_POSTERIOR, BAD_SHAPE = range(10)

_VECTOR = float64[::1]
_MATRIX = float64[:, ::1]
_OUTCOME = types.Tuple((int64, float64))  # (outcome, NIS)


@njit(cache=True)
def merwe_sigma_points(x: np.ndarray, P: np.ndarray, scale: float) -> tuple[np.ndarray, bool]:
    """Merwe sigma points (2n + 1, n) of (x, P) in filterpy's order, scale = sqrt(n + lambda):
    X_0 = x, X_(1+k) = x + scale L[:, k], X_(1+n+k) = x - scale L[:, k] with P = L L^T; and
    whether P is positive definite (the points are not usable when it is not)."""
    sigmas = np.empty((2 * x.size + 1, x.size))
    return sigmas, draw_merwe_sigma_points(sigmas, x, P, scale)


@njit(cache=True)
def draw_merwe_sigma_points(sigmas: np.ndarray, x: np.ndarray, P: np.ndarray, scale: float) -> bool:
    """`merwe_sigma_points` written into ``sigmas`` (2n + 1, n); returns whether P is positive
    definite (``sigmas`` is left as it was when it is not)."""
    n = x.size
    lower, definite = cholesky_lower(P)
    if not definite:
        return False
    sigmas[0] = x
    for k in range(n):
        for a in range(n):
            offset = scale * lower[a, k]  # scale times column k of L
            sigmas[1 + k, a] = x[a] + offset
            sigmas[1 + n + k, a] = x[a] - offset
    return True


@njit(cache=True)
def unscented_transform(
    sigmas_h: np.ndarray, Wm: np.ndarray, Wc: np.ndarray, noise_cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean z = sum_i Wm_i Z_i and covariance sum_i Wc_i (Z_i - z)(Z_i - z)^T plus
    noise_cov of transformed sigma points Z (2n + 1, m), as filterpy's `unscented_transform`."""
    mean, residuals, weighted = _weighted_residuals(sigmas_h, Wm, Wc)
    return mean, weighted.T @ residuals + noise_cov


@njit(cache=True)
def _weighted_residuals(
    sigmas_h: np.ndarray, Wm: np.ndarray, Wc: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean z = sum_i Wm_i Z_i, the residuals Z_i - z (rows) and Wc_i (Z_i - z)."""
    mean = Wm @ sigmas_h
    k, m = sigmas_h.shape
    residuals = np.empty((k, m))
    weighted = np.empty((k, m))
    for i in range(k):
        for a in range(m):
            residuals[i, a] = sigmas_h[i, a] - mean[a]
            weighted[i, a] = Wc[i] * residuals[i, a]
    return mean, residuals, weighted


@njit(cache=True)
def cross_covariance(x: np.ndarray, sigmas: np.ndarray, weighted_h: np.ndarray) -> np.ndarray:
    """P_xz = sum_i Wc_i (X_i - x)(Z_i - z_pred)^T (n, m), from the weighted residuals
    Wc_i (Z_i - z_pred) (rows of ``weighted_h``)."""
    deviations = np.empty_like(sigmas)  # X_i - x
    for i in range(sigmas.shape[0]):
        for a in range(x.size):
            deviations[i, a] = sigmas[i, a] - x[a]
    return deviations.T @ weighted_h


def state_size(n: int, m: int) -> int:
    """Length of the buffer of `filter_arrays` for n states and m measurements."""
    return n + 2 * n * n + (2 * n + 1) * (n + m + 2) + m + m * m + n * m + 4


@njit(cache=True)
def filter_arrays(state: np.ndarray, n: int, m: int):
    """Views of a filter's flat buffer, in this order: x (n,), P (n, n), Q (n, n), the last sigma
    points (2n + 1, n) and their images (2n + 1, m), the last innovation y (m,), its covariance
    S (m, m) and cross-covariance P_xz (n, m), the weights Wm and Wc (2n + 1,), and the scalars
    [sqrt(n + lambda), NIS gate, last NIS, last log-likelihood] (4,).

    The arrays n wide (x to the sigma points) and those m wide (the images to P_xz) follow each
    other, so each group is one matrix whose rows are sliced (one reshape per group: numba's
    reshape is a call into its runtime, a slice of leading rows is not).
    """
    k = 2 * n + 1
    rows_n, rows_m = 4 * n + 2, k + 1 + m + n
    by_n = state[: rows_n * n].reshape(rows_n, n)
    x, P, Q, sigmas = by_n[0], by_n[1 : 1 + n], by_n[1 + n : 1 + 2 * n], by_n[1 + 2 * n :]
    start = rows_n * n
    by_m = state[start : start + rows_m * m].reshape(rows_m, m)
    sigmas_h, y, S, P_xz = by_m[:k], by_m[k], by_m[k + 1 : k + 1 + m], by_m[k + 1 + m :]
    start += rows_m * m
    Wm, Wc, scalars = state[start : start + k], state[start + k : start + 2 * k], state[-4:]
    return x, P, Q, sigmas, sigmas_h, y, S, P_xz, Wm, Wc, scalars


@njit(cache=True)
def same_values(a: np.ndarray, b: np.ndarray | None) -> bool:
    """Whether ``b`` holds the values of ``a`` (same shape, entries equal; NaN equals nothing),
    as ``np.array_equal``; None holds none."""
    if b is None or a.shape != b.shape:
        return False
    flat_a, flat_b = a.ravel(), b.ravel()
    for i in range(flat_a.size):
        if flat_a[i] != flat_b[i]:
            return False
    return True


@njit(cache=True)
def unscented_update(arrays: tuple, z: np.ndarray, R: np.ndarray):
    """Unscented transform, gain and posterior of one update, in place on a filter's arrays
    (`filter_arrays`), from the sigma points and their images already there.

    y, S, P_xz, the NIS and the log-likelihood are written once the NIS is computed; x and P
    only when the update is accepted. Returns (outcome, NIS).
    """
    x, P, _, sigmas, sigmas_h, y_out, S_out, P_xz_out, Wm, Wc, scalars = arrays
    if not all_finite(sigmas_h):
        return BAD_H, math.nan
    # The unscented transform and the cross-covariance share the weighted residuals.
    z_pred, residuals_h, weighted_h = _weighted_residuals(sigmas_h, Wm, Wc)
    S = weighted_h.T @ residuals_h
    for a in range(z.size):
        for b in range(z.size):
            S[a, b] += R[a, b]
    P_xz = cross_covariance(x, sigmas, weighted_h)
    S_lower, definite = cholesky_lower(S)
    if not definite:
        return BAD_S, math.nan
    # With S = L_S L_S^T, W = L_S^-1 P_zx and w = L_S^-1 y: K = P_xz S^-1 = W^T L_S^-1,
    # NIS = y^T S^-1 y = w.w, K y = W^T w and K S K^T = W^T W.
    y = z - z_pred
    W = solve_lower(S_lower, P_xz.T)
    w = solve_lower(S_lower, y.reshape(-1, 1)).ravel()
    nis = w @ w
    log_det_S = 0.0
    for i in range(z.size):
        log_det_S += math.log(S_lower[i, i])
    log_det_S *= 2.0
    log_likelihood = -0.5 * (nis + log_det_S + z.size * math.log(2.0 * math.pi))
    y_out[:], S_out[:], P_xz_out[:] = y, S, P_xz
    scalars[2] = nis
    scalars[3] = log_likelihood if math.isfinite(nis) else -math.inf
    if not math.isfinite(nis):
        return (BAD_NIS if all_finite(z) else BAD_Z), nis
    if nis > scalars[1]:
        return GATED, nis
    P_post = _symmetrised_difference(P, W.T @ W)
    if not cholesky_lower(P_post)[1]:
        return BAD_POSTERIOR, nis
    x += W.T @ w
    P[:] = P_post
    return OK, nis


@njit(cache=True)
def _symmetrised_difference(P: np.ndarray, G: np.ndarray) -> np.ndarray:
    """D = P - G made exactly symmetric, 0.5 (D + D^T), without temporaries."""
    n = P.shape[0]
    out = np.empty((n, n))
    for a in range(n):
        for b in range(a + 1):
            out[a, b] = out[b, a] = 0.5 * ((P[a, b] - G[a, b]) + (P[b, a] - G[b, a]))
    return out


@njit(cache=True)
def _predict_and_draw(arrays: tuple, R: np.ndarray, predict_first: bool):
    """The pending predict (P += Q) if any, the checks of R and P, and the sigma points of (x, P)
    into the filter's arrays; returns OK or the outcome that ends the update."""
    x, P, Q, sigmas, _, _, _, _, _, _, scalars = arrays
    if predict_first:
        P += Q
    if not all_finite(R):
        return BAD_R
    if not draw_merwe_sigma_points(sigmas, x, P, scalars[0]):
        return BAD_P
    return OK


@njit(
    _OUTCOME(_VECTOR, int64, int64, _VECTOR, _MATRIX, _VECTOR, _MATRIX, boolean),
    cache=True,
)
def update_linear(state, n, m, z, A, b, R, predict_first):
    """One update with the linear measurement h(X) = A X + b (A (m, n), b (m,)): sigma points,
    their images, `unscented_update`; after the pending predict if ``predict_first``."""
    if z.shape != (m,) or A.shape != (m, n) or b.shape != (m,) or R.shape != (m, m):
        return BAD_SHAPE, math.nan
    arrays = filter_arrays(state, n, m)
    outcome = _predict_and_draw(arrays, R, predict_first)
    if outcome != OK:
        return outcome, math.nan
    sigmas, sigmas_h = arrays[3], arrays[4]
    np.dot(sigmas, A.T, sigmas_h)  # Z_i = A X_i + b
    for i in range(sigmas_h.shape[0]):
        for r in range(m):
            sigmas_h[i, r] += b[r]
    return unscented_update(arrays, z, R)


@njit(types.Tuple((int64, _MATRIX))(_VECTOR, int64, int64, _MATRIX, boolean), cache=True)
def draw_sigma_points(state, n, m, R, predict_first):
    """First half of an update with a measurement function evaluated outside: the pending
    predict, the checks of R and P, and a copy of the sigma points drawn into the buffer."""
    arrays = filter_arrays(state, n, m)
    return _predict_and_draw(arrays, R, predict_first), arrays[3].copy()


@njit(_OUTCOME(_VECTOR, int64, int64, _MATRIX, _VECTOR, _MATRIX), cache=True)
def update_from_images(state, n, m, sigmas_h, z, R):
    """Second half: `unscented_update` with the images of the sigma points computed outside."""
    arrays = filter_arrays(state, n, m)
    arrays[4][:] = sigmas_h
    return unscented_update(arrays, z, R)
