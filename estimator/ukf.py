"""Unscented Kalman filters with batched measurement functions.

`BatchedUKF` is an additive-noise UKF for a *constant* state (x_{k+1} = x_k + w, w ~ N(0, Q)) whose
measurement function maps all sigma points at once, ``hx_batch(sigmas (n_sigma, n)) -> (n_sigma,
m)``. Its sigma points and weights are those of filterpy's `MerweScaledSigmaPoints` (the object
is kept as ``points``) and a step reproduces filterpy 2.0's stock `UnscentedKalmanFilter` (fx =
identity, the same sigma-point parameters, Q and R) to rounding (the tests hold it to 1e-9 over
50 steps), without the stock filter's Python loops over sigma points.

How it matches filterpy 2.0, step by step:

- filterpy's ``predict`` draws sigma points of (x, P), passes them through fx and takes their
  unscented transform plus Q. With fx = identity the Merwe points satisfy the UT identity exactly
  in real arithmetic (mean x, covariance P), so ``predict`` here is the closed form x, P + Q. In
  floating point filterpy's route differs by about 1e-15 relative (and leaves P asymmetric at that
  level); the closed form is the more accurate of the two and costs no Cholesky.
- filterpy's ``predict`` then redraws the sigma points from the predicted (x, P), and ``update``
  uses those. ``update`` here draws them from the current (x, P) at update time, which is the same
  after a predict and is also correct when several updates follow one predict (filterpy would
  reuse stale points there).
- z_pred, S and P_xz are filterpy's `unscented_transform(sigmas_h, Wm, Wc, R)` and its
  cross-covariance, and the gain, innovation and posterior are filterpy's (K = P_xz S^-1, x += K
  y, P -= K S K^T), in exact arithmetic. They are computed from the differences Z_i - Z_0 of the
  hx outputs (exact to rounding however large Z is against its spread), and the gain through one
  Cholesky factorisation of a joint matrix of S, P_xz and y (`BatchedUKF._init_update_buffers`
  spells it out); to rounding the results are filterpy's, and as accurate (on random problems
  their errors against an extended-precision reference are distributed as those of the previous
  implementation, which formed the terms one at a time). An update that fails any check is sorted
  out step by step in that previous form (`BatchedUKF._update_checked`), and the tests hold the
  two paths to each other.

Why it is fast: predict + update_linear of `InertialParamUKF` (n = 10, m = 6) takes about 12 us in
a tight loop on the 2-core development machine and 14.7 to 14.9 us in
``scripts/benchmark_performance.py --only estimator`` (which interleaves it with filterpy's stock
filter given the same per-point measurement function: 157 to 158 us, 10.5 to 10.7 times longer;
in the same three runs the previous implementation of this module, commit fe1c87d, took 19.3 us,
the stock filter 8.2 times longer). One vectorised hx call and no Python loop over sigma points, no
Cholesky in ``predict``, and about twenty calls into BLAS and LAPACK through scipy's wrappers with
positional arguments and in-place outputs: at this size per-call overhead, not arithmetic, is what
costs, about 0.1 us for a level-1 BLAS call on a vector and 0.2 to 0.5 us for a small gemm or
potrf, against 0.4 to 1 us for an ``np.dot`` or a numpy operation on a strided or broadcast
operand. Run with OPENBLAS_NUM_THREADS=1, as BLAS threads only slow matrices this small (on a busy
machine a thread hand-off can cost milliseconds: measured 8 ms instead of 20 us per update with
two threads while other processes ran; the scripts and the tests set it).

Robustness, beyond filterpy: inputs are shape-checked (ValueError naming the expected shape); an
update with NaN or inf in z, R or the hx output is skipped and counted; S and the posterior P are
Cholesky-checked and an update failing either is rejected and counted; an innovation whose NIS
exceeds ``gate_nis`` is rejected and counted. A rejected or skipped update leaves x and P as they
were. P stays exactly symmetric: P0 and Q are symmetrised on entry and the posterior subtracts a
symmetric product W W^T (BLAS syrk), so 0.5 (P + P^T) would be a no-op.

`InertialParamUKF` filters a rigid body's 10 standard inertial parameters pi, whose measurements
(the wrench balance) are linear, and reports the physically consistent body of highest posterior
density (`constrained_mode`: about 110 us per call on states recorded from the environment,
against about 600 us for the previous, plain implementation, kept as `_barrier_mode_reference`).
`LogCholeskyUKF` filters in log-Cholesky coordinates eta instead, so that every sigma
point is a realisable body (the design DESIGN.md recommends); it is kept as the measured reference
for that choice: on recordings of a weakly exciting 90 s nominal tumble it ends with a normalised
estimation error squared of 10^3 to 10^5 for 10 parameters, against about 11 for
`InertialParamUKF` on the very same measurements (scripts/benchmark_estimation.py reports both
for every case). See `InertialParamUKF`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform
from scipy.linalg.blas import daxpy as _axpy
from scipy.linalg.blas import dcopy as _copy
from scipy.linalg.blas import ddot as _dot
from scipy.linalg.blas import dgemm as _gemm
from scipy.linalg.blas import dgemv as _gemv
from scipy.linalg.blas import dsyrk as _syrk
from scipy.linalg.lapack import dposv as _posv
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dtrtri as _trtri
from scipy.linalg.lapack import dtrtrs as _trtrs

from .inertia import (
    log_cholesky_to_params,
    mass_com_inertia_from_params,
    params_to_log_cholesky,
    params_to_pseudo_inertia,
    physical_violation,
    project_physical,
)

__all__ = [
    "BatchedUKF",
    "InertialParamUKF",
    "LogCholeskyUKF",
    "UpdateResult",
    "constrained_mode",
    "linear_params_hx",
]

# Default Merwe parameters. With n = 10, alpha = 0.5 and kappa = 0 give lambda = -7.5, a spread of
# sqrt(n + lambda) = 1.58 standard deviations per axis, Wm0 = -3 and Wc0 = -0.25. kappa = 3 - n
# would give Wm0 = -12.3 and Wc0 = -9.6 (the huge negative weights that make the transformed
# covariance indefinite), and alpha = 1 spreads the points 3.2 standard deviations out, far into
# the nonlinearity of exp() in the log-Cholesky map.
DEFAULT_ALPHA = 0.5
DEFAULT_BETA = 2.0
DEFAULT_KAPPA = 0.0

N_INERTIAL_PARAMS = 10

# Diagonal of the trailing block of the joint matrix factored in `BatchedUKF.update`: large enough
# to keep those pivots positive for any sensible K and NIS (a failure there only sends the update
# down the step-by-step path), small enough that no product of its factor underflows.
_TRAILING_PIVOT = 1e100


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one measurement update.

    accepted: whether x and P were changed.
    reason: "ok", "non-finite" (NaN/inf in z, R or the hx output), "gated" (NIS above the gate)
        or "not-positive-definite" (S or the posterior P failed its Cholesky).
    nis: normalised innovation squared y^T S^-1 y (NaN when it could not be computed).
    """

    accepted: bool
    reason: str
    nis: float


def _as_square_matrix(value: np.ndarray | float, dim: int, name: str) -> np.ndarray:
    """Return `value` as a float (dim, dim) array; a ValueError names the expected shape."""
    matrix = np.asarray(value, dtype=float)
    if matrix.shape != (dim, dim):
        raise ValueError(f"{name} must have shape ({dim}, {dim}), got {matrix.shape}")
    return matrix


def _all_finite(array: np.ndarray) -> bool:
    """True if no entry is NaN or inf. A dot product is the cheap test at these sizes (NaN and inf
    propagate into it, and BLAS raises no warnings); only on overflow does the exact test run."""
    flat = array.ravel()
    return math.isfinite(np.dot(flat, flat)) or bool(np.isfinite(array).all())


def _cholesky_lower(matrix: np.ndarray) -> tuple[np.ndarray, int]:
    """Lower Cholesky factor via LAPACK potrf (a quarter of np.linalg.cholesky's call overhead
    at n = 10); info != 0 when the matrix is not positive definite. Reads the lower triangle."""
    return _potrf(matrix, 1, 1)  # (a, lower, clean); positional: f2py parses keywords slowly


def _solve_lower(lower: np.ndarray, rhs: np.ndarray, transpose: bool = False) -> np.ndarray:
    """L^-1 rhs (or L^-T rhs) for a lower-triangular L (LAPACK trtrs; Fortran-ordered rhs avoids
    a copy)."""
    solution, _ = _trtrs(lower, rhs, 1, int(transpose))  # (a, b, lower, trans)
    return solution


def linear_params_hx(
    A: np.ndarray,
    b: np.ndarray,
    to_params: Callable[[np.ndarray], np.ndarray] | None = log_cholesky_to_params,
) -> Callable[[np.ndarray], np.ndarray]:
    """Batched measurement function of z = A pi(x) + b: sigma points (k, 10) -> (k, m).

    A is (m, 10) and b (m,); pi(x) is ``to_params`` (`log_cholesky_to_params` for the state of
    `LogCholeskyUKF`; None when the state is pi itself, as in `InertialParamUKF`).
    """
    return _linear_hx(np.asarray(A, dtype=float), np.asarray(b, dtype=float), to_params)


def _linear_hx(
    A: np.ndarray, b: np.ndarray, to_params: Callable[[np.ndarray], np.ndarray] | None
) -> Callable[[np.ndarray], np.ndarray]:
    """`linear_params_hx` for float arrays A (m, 10) and b (m,)."""
    A_T = A.T
    m = len(b)

    def hx_batch(sigmas: np.ndarray) -> np.ndarray:
        params = sigmas if to_params is None else to_params(sigmas)
        if params.ndim != 2:
            return np.dot(params, A_T) + b
        # [A pi_1 + b, ...]^T in one BLAS gemm (beta = 1 on copies of b), written in place
        # through the transposed view: half the cost of np.dot(params, A.T) + b at this size.
        out = np.empty((len(params), m))
        out[...] = b
        _gemm(1.0, A_T, params.T, 1.0, out.T, 1, 0, 1)
        return out

    return hx_batch


class BatchedUKF:
    """Additive-noise UKF with an identity process model and a batched measurement function.

    Args:
        dim_x: state dimension n.
        dim_z: measurement dimension m.
        x0: initial mean, shape (n,).
        P0: initial covariance, (n, n), symmetric positive definite.
        Q: process noise covariance per `predict`, (n, n).
        alpha, beta, kappa: Merwe scaled sigma-point parameters (see `DEFAULT_ALPHA`).
        gate_nis: reject updates whose NIS exceeds this (e.g. ``scipy.stats.chi2.ppf(0.999, m)``);
            None disables gating.

    Attributes: x, P (current mean and covariance); y, S, K, nis, log_likelihood (innovation, its
    covariance, the gain, the NIS and the Gaussian log-likelihood of the last update that got that
    far, gated or not); sigmas, sigmas_h (the last sigma points and their images); counters
    n_updates (accepted), n_skipped_nonfinite, n_gated, n_rejected_not_pd; points (the filterpy
    sigma-point object), Wm, Wc (its weights).
    """

    def __init__(
        self,
        dim_x: int,
        dim_z: int,
        x0: np.ndarray,
        P0: np.ndarray,
        Q: np.ndarray,
        alpha: float = DEFAULT_ALPHA,
        beta: float = DEFAULT_BETA,
        kappa: float = DEFAULT_KAPPA,
        gate_nis: float | None = None,
    ) -> None:
        if dim_x < 1 or dim_z < 1:
            raise ValueError(f"dim_x and dim_z must be >= 1, got {dim_x} and {dim_z}")
        if gate_nis is not None and not gate_nis > 0.0:
            raise ValueError(f"gate_nis must be positive or None, got {gate_nis}")
        self.dim_x = int(dim_x)
        self.dim_z = int(dim_z)
        self.points = MerweScaledSigmaPoints(self.dim_x, alpha=alpha, beta=beta, kappa=kappa)
        self.Wm = self.points.Wm
        self.Wc = self.points.Wc
        self.n_sigma = self.points.num_sigmas()
        lambda_ = alpha**2 * (self.dim_x + kappa) - self.dim_x
        if not self.dim_x + lambda_ > 0.0:
            raise ValueError(
                f"alpha^2 (n + kappa) must be positive, got alpha={alpha}, kappa={kappa}"
            )
        # filterpy's points are x +- rows of U, U^T U = (n + lambda) P, i.e. x +- sqrt(n + lambda)
        # times the columns of the lower Cholesky factor L of P: sigmas = x + offsets @ L^T.
        sigma_scale = math.sqrt(self.dim_x + lambda_)
        eye = np.eye(self.dim_x)
        self._sigma_offsets = np.vstack(
            (np.zeros(self.dim_x), sigma_scale * eye, -sigma_scale * eye)
        )
        # Cross-covariance sum_i Wc_i (X_i - x)(Z_i - z_pred)^T: X_0 - x = 0 and X_i - x = +-
        # sqrt(n + lambda) L columns share the weight Wc_1, so z_pred cancels and
        # P_xz = L (cross_weights @ Z) with cross_weights = Wc_1 sqrt(n + lambda) [0, 1, -1].
        self._cross_weights = (float(self.Wc[1]) * self._sigma_offsets).T.copy()
        self._init_update_buffers()

        self.gate_nis = gate_nis

        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (self.dim_x,):
            raise ValueError(f"x0 must have shape ({self.dim_x},), got {x0.shape}")
        P0 = _as_square_matrix(P0, self.dim_x, "P0")
        if not _all_finite(x0) or not _all_finite(P0):
            raise ValueError("x0 and P0 must be finite")
        try:
            np.linalg.cholesky(P0)
        except np.linalg.LinAlgError:
            raise ValueError("P0 must be symmetric positive definite") from None
        self.x = x0.copy()
        self.P = 0.5 * (P0 + P0.T)
        self.Q = self._checked_Q(Q)

        self.y = np.zeros(self.dim_z)
        self.S = np.zeros((self.dim_z, self.dim_z))
        self.nis = math.nan
        self._S_lower = np.eye(self.dim_z)
        self._W_T = np.zeros((self.dim_z, self.dim_x))  # L_S^-1 P_zx, so that K = W L_S^-1
        self._factors: np.ndarray | None = None  # the joint factor of a fast-path update
        self.sigmas = np.zeros((self.n_sigma, self.dim_x))
        self.sigmas_h = np.zeros((self.n_sigma, self.dim_z))
        self.n_updates = 0
        self.n_skipped_nonfinite = 0
        self.n_gated = 0
        self.n_rejected_not_pd = 0

    def _init_update_buffers(self) -> None:
        """Constant matrices and work buffers of `update`.

        At n = 10, m = 6 a numpy, BLAS or LAPACK call costs 0.1 to 1 us of overhead and next to
        nothing in arithmetic, so an update is laid out as few calls as possible (and as the
        cheapest kinds of call, see the module docstring):

        1. L = chol(P), LAPACK potrf in place in ``_x_L`` = [x, L]; sigma points
           [1, offsets] @ [x, L]^T, one BLAS gemm.
        2. Z = hx(sigma points). One gemm of a constant matrix with Z gives, as rows of
           ``_stack``: E = sqrt(n + lambda) (Z_(1+r) - Z_(1+n+r)) (r < n, so that P_xz =
           Wc_1 L E), the differences D_i = Z_i - Z_0 (i = 1..2n), their sum s, -z_pred and
           (gamma / Wc_1) s. With G_i = Z_i - z_pred = D_i - Wm_1 s (D_0 = 0) the covariance of
           the residuals is sum_i Wc_i G_i G_i^T = Wc_1 sum_i D_i D_i^T + gamma s s^T, gamma =
           Wm_1^2 sum_i Wc_i - 2 Wc_1 Wm_1. The differences are exact to rounding, however
           large Z is against its spread (residuals taken from a weighted mean, as filterpy
           does, lose about eps |Z| each); s s^T carries the rest, which is small (it vanishes
           for a linear hx). R and z are copied into ``_stack`` too, so that one dot product of
           ``_stack`` with itself tests R, z and Z for NaN and inf.
        3. One gemm Wc_1 ``_picks`` @ ``_stack`` gives the first m columns [S; P_xz; y^T] of
           the joint matrix [[S, ., .], [P_xz, c I, .], [y^T, 0, c]] (only its lower triangle
           is read; c I is a constant that keeps the trailing pivots positive).
        4. One Cholesky factorisation (potrf) of the joint matrix holds L_S, W = P_xz L_S^-T
           and w^T = (L_S^-1 y)^T: what a Cholesky of S and a triangular solve would give, in
           one call. It fails if S is not positive definite.
        5. K S K^T = W W^T (BLAS syrk, exactly symmetric), K y = W w and the NIS w.w. The
           posterior P - W W^T is Cholesky-checked (potrf) as it is kept.
        """
        n, m, k = self.dim_x, self.dim_z, self.n_sigma
        wc1, wm1 = float(self.Wc[1]), float(self.Wm[1])
        gamma = wm1**2 * float(self.Wc.sum()) - 2.0 * wc1 * wm1
        sigma_scale = float(self._sigma_offsets[1, 0])
        differences = np.hstack((-np.ones((2 * n, 1)), np.eye(2 * n)))  # D_i = Z_i - Z_0
        sums = differences.sum(axis=0, keepdims=True)  # s = sum_i D_i
        # Rows of `_stack` (each m wide), the contraction index of step 3:
        #   [0, m) R | m z | m + 1 zero | E (n) | D (2n) | (gamma / Wc_1) s | -z_pred || s
        # Those from E on are the gemm of step 2; the last one is not part of the contraction.
        e0 = m + 2
        d0 = e0 + n
        s0 = d0 + 2 * n
        n_left = s0 + 2
        self._from_h_T = np.vstack(
            (
                sigma_scale * (np.eye(k)[1 : n + 1] - np.eye(k)[n + 1 :]),
                differences,
                (gamma / wc1) * sums,
                -self.Wm[None, :],
                sums,
            )
        ).T
        self._stack = np.zeros((n_left + 1, m))
        self._stack_flat = self._stack.ravel()
        self._stack_R = self._stack[:m]
        self._stack_z = self._stack[m]
        self._stack_from_h_T = self._stack[e0:].T
        self._stack_left_T = self._stack[:n_left].T
        self._stack_D_T = self._stack[d0:s0].T
        self._stack_s = self._stack[n_left]
        # `_picks` (m + n + 1, n_left): row j of the gemm of step 3 (times Wc_1) takes
        #   j < m:          e_j / Wc_1 on R, D^T_j on D, s_j on (gamma / Wc_1) s   -> S_j
        #   m <= j < m + n: [x, L]_(j-m) on [zero, E]                              -> P_xz
        #   m + n:          1 / Wc_1 on z and on -z_pred                           -> y
        self._picks = np.zeros((m + n + 1, n_left))
        self._picks[:m, :m] = np.eye(m) / wc1
        self._picks[m + n, m] = 1.0 / wc1
        self._picks[m + n, s0 + 1] = 1.0 / wc1
        self._picks_T = self._picks.T
        self._picks_x_L = self._picks[m : m + n, m + 1 : d0]
        self._picks_D_T = self._picks[:m, d0:s0]
        self._picks_s = self._picks[:m, s0]
        self._wc1 = wc1
        # [x, L] (n, n + 1), Fortran-ordered: potrf factors P in place in its last n columns.
        self._x_L = np.zeros((n, n + 1), order="F")
        self._x_L_x = self._x_L[:, 0]
        self._x_L_L = self._x_L[:, 1:]
        self._ones_offsets_T = np.hstack((np.ones((k, 1)), self._sigma_offsets)).T
        self._joint_template = np.zeros((m + n + 1, m + n + 1), order="F")
        self._joint_template[range(m, m + n + 1), range(m, m + n + 1)] = _TRAILING_PIVOT
        # What `update` reads, in one tuple (one attribute lookup instead of twenty).
        self._update_buffers = (
            self._x_L,
            self._x_L_L,
            self._x_L_x,
            self._ones_offsets_T,
            self._from_h_T,
            self._stack_from_h_T,
            self._stack_R,
            self._stack_z,
            self._stack_flat,
            self._picks_x_L,
            self._picks_D_T,
            self._stack_D_T,
            self._picks_s,
            self._stack_s,
            self._joint_template,
            self._picks_T,
            self._stack_left_T,
        )

    def _checked_Q(self, Q: np.ndarray) -> np.ndarray:
        Q = _as_square_matrix(Q, self.dim_x, "Q")
        if not _all_finite(Q):
            raise ValueError("Q must be finite")
        # A symmetric Q keeps P exactly symmetric through predict.
        return 0.5 * (Q + Q.T)

    def _factor_P(self) -> int:
        """L = chol(P) into ``_x_L`` (LAPACK potrf in place); info != 0 if P is not positive
        definite."""
        self._x_L_L[...] = self.P
        return _potrf(self._x_L_L, 1, 1, 1)[1]  # (a, lower, clean, overwrite_a)

    def _sigmas_from_factor(self) -> np.ndarray:
        """Sigma points x + offsets @ L^T = [1, offsets] @ [x, L]^T, one BLAS gemm, from the L
        that `_factor_P` left in ``_x_L`` (`update` does the very same)."""
        self._x_L_x[...] = self.x
        return _gemm(1.0, self._x_L, self._ones_offsets_T).T

    def sigma_points(self) -> np.ndarray:
        """Merwe sigma points of the current (x, P), shape (2n + 1, n), filterpy's ordering.

        Raises np.linalg.LinAlgError if P is not positive definite.
        """
        if self._factor_P() != 0:
            raise np.linalg.LinAlgError("P is not positive definite")
        return self._sigmas_from_factor()

    def predict(self, Q: np.ndarray | None = None) -> None:
        """Propagate through x_{k+1} = x_k + w: x is unchanged, P grows by Q (or by `self.Q`).

        This is the unscented transform of the identity map in closed form (see the module
        docstring).
        """
        self.P = self.P + (self.Q if Q is None else self._checked_Q(Q))

    def update(
        self,
        z: np.ndarray,
        hx_batch: Callable[[np.ndarray], np.ndarray],
        R: np.ndarray,
    ) -> UpdateResult:
        """Fuse measurement z ~ N(h(x), R), with h given for all sigma points by `hx_batch`.

        Args:
            z: measurement, shape (m,).
            hx_batch: maps sigma points (2n + 1, n) to predicted measurements (2n + 1, m).
            R: measurement noise covariance, (m, m).

        Returns an `UpdateResult`; when it is not accepted, x and P are unchanged.
        """
        m = self.dim_z
        z = np.asarray(z, dtype=float)
        if z.shape != (m,):
            raise ValueError(f"z must have shape ({m},), got {z.shape}")
        R = np.asarray(R, dtype=float)
        if R.shape != (m, m):
            raise ValueError(f"R must have shape ({m}, {m}), got {R.shape}")

        # The steps of `_init_update_buffers`, written out (a method call costs here). Any
        # failure (non-finite input, a Cholesky that fails, a non-finite NIS) hands the update
        # to `_update_checked`, which sorts it out one check at a time.
        (
            x_L,
            x_L_L,
            x_L_x,
            ones_offsets_T,
            from_h_T,
            stack_from_h_T,
            stack_R,
            stack_z,
            stack_flat,
            picks_x_L,
            picks_D_T,
            stack_D_T,
            picks_s,
            stack_s,
            joint_template,
            picks_T,
            stack_left_T,
        ) = self._update_buffers
        P = self.P
        x_L_L[...] = P
        if _potrf(x_L_L, 1, 1, 1)[1] != 0:  # (a, lower, clean, overwrite_a)
            return self._update_checked(z, hx_batch, R)
        x_L_x[...] = self.x
        sigmas = _gemm(1.0, x_L, ones_offsets_T).T
        sigmas_h = np.asarray(hx_batch(sigmas), dtype=float)
        if sigmas_h.shape != (self.n_sigma, m):
            return self._update_checked(z, hx_batch, R, sigmas, sigmas_h)
        # gemm arguments: (alpha, a, b, beta, c, trans_a, trans_b, overwrite_c), positional as
        # f2py parses keywords slowly; c is a Fortran-ordered view of the buffer, so written in
        # place. Unlike np.dot, scipy's BLAS wrappers do not warn about an inf in Z.
        _gemm(1.0, sigmas_h.T, from_h_T, 0.0, stack_from_h_T, 0, 0, 1)
        stack_R[...] = R
        stack_z[...] = z
        if not (math.isfinite(_dot(stack_flat, stack_flat)) or np.isfinite(stack_flat).all()):
            return self._update_checked(z, hx_batch, R, sigmas, sigmas_h)
        picks_x_L[...] = x_L
        picks_D_T[...] = stack_D_T
        picks_s[...] = stack_s
        n = self.dim_x
        joint = joint_template.copy("F")
        _gemm(self._wc1, picks_T, stack_left_T, 0.0, joint[:, :m], 1, 1, 1)
        factor = joint.copy("F")
        if _potrf(factor, 1, 1, 1)[1] != 0:  # in place (joint keeps S and y)
            return self._update_checked(z, hx_batch, R, sigmas, sigmas_h)
        W = factor[m : m + n, :m]
        # w = factor[m + n, :m]: m entries from m + n on, m + n + 1 apart in Fortran order. The
        # BLAS wrappers take such strides (ddot (x, y, n, offx, incx, offy, incy)).
        factor_flat = factor.T.ravel()
        d = m + n + 1
        nis = _dot(factor_flat, factor_flat, m, m + n, d, m + n, d)
        if not math.isfinite(nis):
            return self._update_checked(z, hx_batch, R, sigmas, sigmas_h)
        self.sigmas = sigmas
        self.sigmas_h = sigmas_h
        self.y = joint[m + n, :m]
        self.S = joint[:m, :m]
        self.nis = nis
        self._factors = factor
        if self.gate_nis is not None and nis > self.gate_nis:
            self.n_gated += 1
            return UpdateResult(False, "gated", nis)
        # K S K^T = W W^T (BLAS syrk through np.dot: exactly symmetric, so P stays so) and
        # K y = W w (gemv (alpha, a, x, beta, y): x + W w in a new array).
        P_post = P - np.dot(W, W.T)
        if _potrf(P_post.T, 1, 0)[1] != 0:  # (P_post.T: the same matrix, Fortran-ordered)
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", nis)
        self.P = P_post
        # (alpha, a, x, beta, y, offx, incx): x + W w in a new array.
        self.x = _gemv(1.0, W, factor_flat, 1.0, self.x, m + n, d)
        self.n_updates += 1
        return UpdateResult(True, "ok", nis)

    def _update_checked(
        self,
        z: np.ndarray,
        hx_batch: Callable[[np.ndarray], np.ndarray],
        R: np.ndarray,
        sigmas: np.ndarray | None = None,
        sigmas_h: np.ndarray | None = None,
    ) -> UpdateResult:
        """`update` one check at a time (z and R are shape-checked float arrays): the path of
        every update that fails somewhere, and the reference for the fast path. Given the sigma
        points and their hx outputs (from the same x and P) it does not call hx again."""
        m = self.dim_z
        # z is checked through the NIS: NaN or inf in z makes y, hence the NIS, non-finite.
        if not _all_finite(R):
            self.n_skipped_nonfinite += 1
            return UpdateResult(False, "non-finite", math.nan)

        if self._factor_P() != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", math.nan)
        P_lower = self._x_L_L
        if sigmas_h is None:
            sigmas = self._sigmas_from_factor()
            sigmas_h = np.asarray(hx_batch(sigmas), dtype=float)
        if sigmas_h.shape != (self.n_sigma, m):
            raise ValueError(
                f"hx_batch must return shape ({self.n_sigma}, {m}) for sigma points of shape "
                f"{sigmas.shape}, got {sigmas_h.shape}"
            )
        self.sigmas = sigmas
        self.sigmas_h = sigmas_h
        if not _all_finite(sigmas_h):
            self.n_skipped_nonfinite += 1
            return UpdateResult(False, "non-finite", math.nan)

        n = self.dim_x
        # rhs_T = [P_xz; -z_pred] = [L cross_weights; -Wm] Z. S is filterpy's
        # unscented_transform(sigmas_h, Wm, Wc, R) written out, sharing z_pred with the
        # cross-covariance.
        rhs_T = np.dot(np.vstack((np.dot(P_lower, self._cross_weights), -self.Wm)), sigmas_h)
        residuals_h = sigmas_h + rhs_T[n]
        S = np.dot(residuals_h.T * self.Wc, residuals_h)
        S += R
        y = rhs_T[n]
        y += z
        # The Cholesky S = L_S L_S^T also checks S is positive definite (a negative Wc0 can make
        # it indefinite). With [W^T, w] = L_S^-1 [P_zx, y]: NIS = w.w, K S K^T = P_xz S^-1 P_zx
        # = W W^T and K y = W w.
        S_lower, info = _cholesky_lower(S)
        if info != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", math.nan)
        whitened = _solve_lower(S_lower, rhs_T.T)
        W_T, w = whitened[:, :n], whitened[:, n]
        nis = float(np.dot(w, w))
        self.y, self.S, self.nis, self._S_lower, self._W_T = y, S, nis, S_lower, W_T
        self._factors = None
        if not math.isfinite(nis):
            if _all_finite(z):
                self.n_rejected_not_pd += 1
                return UpdateResult(False, "not-positive-definite", nis)
            self.n_skipped_nonfinite += 1
            return UpdateResult(False, "non-finite", nis)
        if self.gate_nis is not None and nis > self.gate_nis:
            self.n_gated += 1
            return UpdateResult(False, "gated", nis)

        # W W^T is a symmetric rank-m product (numpy calls BLAS syrk for a.T @ a), so P_post is
        # exactly symmetric: 0.5 (P + P^T) would change nothing. The Cholesky checks it is
        # positive definite.
        P_post = self.P - np.dot(W_T.T, W_T)
        _, info = _cholesky_lower(P_post)
        if info != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", nis)
        self.x = self.x + np.dot(W_T.T, w)
        self.P = P_post
        self.n_updates += 1
        return UpdateResult(True, "ok", nis)

    def _last_factors(self) -> tuple[np.ndarray, np.ndarray]:
        """L_S and W^T = L_S^-1 P_zx of the last update that computed an innovation."""
        if self._factors is None:
            return self._S_lower, self._W_T
        m = self.dim_z
        return self._factors[:m, :m], self._factors[m : m + self.dim_x, :m].T

    @property
    def K(self) -> np.ndarray:
        """Kalman gain P_xz S^-1 (n, m) of the last update that computed an innovation."""
        S_lower, W_T = self._last_factors()
        return _solve_lower(S_lower, W_T, transpose=True).T

    @property
    def log_likelihood(self) -> float:
        """Gaussian log-likelihood of the last innovation y under N(0, S)."""
        if not math.isfinite(self.nis):
            return -math.inf
        log_det_S = 2.0 * float(np.log(np.diag(self._last_factors()[0])).sum())
        return -0.5 * (self.nis + log_det_S + self.dim_z * math.log(2.0 * math.pi))


def _checked_linear_hx(
    A: np.ndarray, b: np.ndarray, m: int, log_cholesky: bool
) -> Callable[[np.ndarray], np.ndarray]:
    """`linear_params_hx` for a state in log-Cholesky coordinates or in pi, after shape checks."""
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    if A.shape != (m, N_INERTIAL_PARAMS):
        raise ValueError(f"A must have shape ({m}, {N_INERTIAL_PARAMS}), got {A.shape}")
    if b.shape != (m,):
        raise ValueError(f"b must have shape ({m},), got {b.shape}")
    # A non-finite A or b makes the hx output non-finite, which `update` checks and counts.
    return _linear_hx(A, b, log_cholesky_to_params if log_cholesky else None)


def _checked_prior(prior_params: np.ndarray) -> np.ndarray:
    prior_params = np.asarray(prior_params, dtype=float)
    if prior_params.shape != (N_INERTIAL_PARAMS,):
        raise ValueError(
            f"prior_params must have shape ({N_INERTIAL_PARAMS},), got {prior_params.shape}"
        )
    return prior_params


# Prior standard deviations for `LogCholeskyUKF` in log-Cholesky coordinates (alpha, d1..3, s12,
# s23, s13, t1..3): mass within a factor ~e^(2*0.5) = 2.7, principal second moments within a
# factor ~e^2, centre of mass within 0.15 m (what CargoEstimator used with it).
LOG_CHOLESKY_PRIOR_STD = np.array([0.5, 1.0, 1.0, 1.0, 0.3, 0.3, 0.3, 0.15, 0.15, 0.15])
LOG_CHOLESKY_PROCESS_STD = 1e-5


class LogCholeskyUKF(BatchedUKF):
    """UKF on a rigid body's inertial parameters, filtered in log-Cholesky coordinates eta.

    The state x is eta (10,); every sigma point maps to a physically realisable body through
    `log_cholesky_to_params`. Parameters are reported in standard form
    pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (h = m c, I about the frame origin).

    Args:
        prior_params: prior mean as standard parameters pi (10,); must be physically realisable.
        prior_std_eta: prior standard deviation(s) in eta, scalar or (10,).
        process_std_eta: random-walk standard deviation(s) of eta per `predict`, scalar or (10,).
        dim_z: rows of the measurement matrices given to `update_linear`.
        alpha, beta, kappa, gate_nis: as for `BatchedUKF`.

    Tuning: pi(eta) is strongly nonlinear (exp and squares), so one update whose R is far tighter
    than the prior's spread of A pi overshoots. From a wrong prior with std 0.5 in eta, noiseless
    measurements filtered with R = 1e-6 I drove the d coordinates to 45 (inertia 1e39) within 5
    updates, while R = 1e-2 I converged consistently (NEES about 5 for 10 states). Keep R honest,
    the prior std per coordinate realistic (alpha and d are logs, s and t lengths in m), and use
    NIS gating.
    """

    def __init__(
        self,
        prior_params: np.ndarray,
        prior_std_eta: float | np.ndarray,
        process_std_eta: float | np.ndarray,
        dim_z: int = 6,
        alpha: float = DEFAULT_ALPHA,
        beta: float = DEFAULT_BETA,
        kappa: float = DEFAULT_KAPPA,
        gate_nis: float | None = None,
    ) -> None:
        eta0 = params_to_log_cholesky(_checked_prior(prior_params))
        super().__init__(
            N_INERTIAL_PARAMS,
            dim_z,
            eta0,
            np.diag(self._variances(prior_std_eta, "prior_std_eta", allow_zero=False)),
            np.diag(self._variances(process_std_eta, "process_std_eta", allow_zero=True)),
            alpha=alpha,
            beta=beta,
            kappa=kappa,
            gate_nis=gate_nis,
        )

    @staticmethod
    def _variances(std: float | np.ndarray, name: str, allow_zero: bool) -> np.ndarray:
        std = np.broadcast_to(np.asarray(std, dtype=float), (N_INERTIAL_PARAMS,))
        ok = std >= 0.0 if allow_zero else std > 0.0
        if not (np.isfinite(std).all() and ok.all()):
            bound = ">= 0" if allow_zero else "> 0"
            raise ValueError(f"{name} must be finite and {bound}, scalar or (10,), got {std}")
        return std**2

    def update_linear(
        self, z: np.ndarray, A: np.ndarray, b: np.ndarray, R: np.ndarray
    ) -> UpdateResult:
        """Fuse z = A pi(eta) + b + v, v ~ N(0, R), with A (m, 10), b (m,), R (m, m)."""
        return self.update(z, _checked_linear_hx(A, b, self.dim_z, True), R)

    def params_mean(self) -> np.ndarray:
        """Standard parameters pi(eta_mean) of the mean state.

        Chosen over the unscented mean of pi because pi(eta_mean) is always a realisable body,
        while a weighted mean with a negative Wm0 need not be.
        """
        return log_cholesky_to_params(self.x)

    def params_cov(self) -> np.ndarray:
        """Covariance (10, 10) of pi: unscented transform of the sigma points of (eta, P)."""
        params_sigmas = log_cholesky_to_params(self.sigma_points())
        _, cov = unscented_transform(params_sigmas, self.Wm, self.Wc)
        return 0.5 * (cov + cov.T)

    def params_std(self) -> np.ndarray:
        """Standard deviations (10,) of pi from `params_cov` (negative rounding clipped to 0)."""
        return np.sqrt(np.maximum(np.diag(self.params_cov()), 0.0))


def _is_physical(pi: np.ndarray) -> bool:
    """Pseudo-inertia positive definite (the Cholesky is the cheapest test); a ValueError (from
    `params_to_pseudo_inertia`) if pi is not a finite (10,) array."""
    pi = np.asarray(pi, dtype=float)
    if pi.shape == (N_INERTIAL_PARAMS,) and math.isfinite(_dot(pi, pi)):
        j = np.dot(pi, _PSEUDO_INERTIA_BASIS).reshape(4, 4)  # params_to_pseudo_inertia, unchecked
    else:
        j = params_to_pseudo_inertia(pi)
    return _potrf(j, 1, 0)[1] == 0  # (a, lower, clean)


# J(pi) = sum_k pi_k E_k: the pseudo-inertia is linear in the standard parameters (E_k flattened
# to rows of 16).
_PSEUDO_INERTIA_BASIS = params_to_pseudo_inertia(np.eye(10)).reshape(10, 16)
_VEC_EYE4 = np.eye(4).ravel()  # tr(C) = C.ravel() @ _VEC_EYE4
_EYE10_F = np.eye(10, order="F")


def constrained_mode(
    mean: np.ndarray,
    cov: np.ndarray,
    start: np.ndarray | None = None,
    gap: float = 1e-4,
) -> tuple[np.ndarray, bool]:
    """The physically consistent body of highest density under N(mean, cov): (pi, solved).

    Minimises the Mahalanobis distance 0.5 (pi - mean)^T cov^-1 (pi - mean) over bodies whose
    pseudo-inertia J(pi) is positive definite. J is linear in pi, so this is a convex problem (a
    small semidefinite program): solved by a log-barrier interior-point method, Newton steps on
    0.5 |v|^2 - t log det J(mean + L v) in whitened coordinates v (cov = L L^T), t divided by 50
    from 1 down to ``gap`` / 4 (the barrier's bound on the remaining excess of the half squared
    distance is 4 t for a 4 x 4 J), each step backtracked so that J stays positive definite. It
    starts from the eigenvalue-clipped pseudo-inertia of ``mean`` or from ``start`` (a consistent
    body, such as the previous mode of a filter whose state moved a little), whichever is nearer.
    A consistent ``mean`` is its own mode (returned as a copy without iterating). The result is
    always strictly consistent: should the iteration break down numerically (a covariance that
    is not positive definite, an overflow next to the boundary), it returns the eigenvalue-clipped
    body with ``solved`` False.

    Where the iterate stops depends on the path: Newton stops once its decrement is below
    ``gap`` / 10, on states recorded from the environment 1e-6 relative (at most 2e-4) from the
    exact minimiser of the last barrier problem. So the path is part of the result, and
    `_barrier_mode` keeps the one of the plain computation (`_barrier_mode_reference`) step for
    step, with fewer and cheaper calls: on 888 recorded states they agree to 5e-16 relative, at
    about 110 us per call against 600 us.
    """
    mean = np.asarray(mean, dtype=float)
    if _is_physical(mean):
        return mean.copy(), True
    clipped = project_physical(mean, min_eig=1e-3)
    # Should the fast iteration break down (or end on a body that J(pi), recomputed, finds just
    # outside: it updates J incrementally, so next to a singular J rounding can decide), the
    # plain one decides, as before.
    for barrier_mode in (_barrier_mode, _barrier_mode_reference):
        try:
            with np.errstate(over="raise", divide="raise", invalid="raise"):
                pi = barrier_mode(mean, cov, clipped, start, gap)
        except (np.linalg.LinAlgError, FloatingPointError, ValueError):
            continue
        if _is_physical(pi):
            return pi, True
    return clipped, False


def _barrier_start(
    mean: np.ndarray, lower: np.ndarray, clipped: np.ndarray, start: np.ndarray | None
) -> tuple[np.ndarray, float]:
    """Whitened starting point v (cov = L L^T) and barrier weight t of `constrained_mode`: the
    clipped body at t = 1, or ``start`` further down the central path (t = 1e-2) if it is
    consistent and nearer the mean."""
    v = _solve_lower(lower, clipped - mean)
    if start is not None and _is_physical(start):
        v_start = _solve_lower(lower, np.asarray(start, dtype=float) - mean)
        if _dot(v_start, v_start) < _dot(v, v):
            return v_start, 1e-2
    return v, 1.0


def _barrier_mode(
    mean: np.ndarray,
    cov: np.ndarray,
    clipped: np.ndarray,
    start: np.ndarray | None,
    gap: float,
) -> np.ndarray:
    """The interior-point iteration of `constrained_mode` (may raise on numerical trouble): the
    steps of `_barrier_mode_reference`, computed with fewer and cheaper calls.

    A call takes about 25 barrier evaluations and 20 Newton systems, each a handful of BLAS and
    LAPACK calls on 4 x 4 and 10 x 10 matrices, so what costs is the number of calls and their
    kind (scipy's wrappers of level-1 BLAS on vectors cost a tenth of an ``np.dot``):

    - J is linear in v: J(v) = J(mean) + sum_l v_l B_l with B_l = sum_k L_kl E_k, so a trial
      point's J is J(v) - s J(u) (u the Newton direction), one axpy (J(v) is updated the same
      way; rounding can therefore make J(pi) of the result, recomputed, differ from it where J
      is singular to working precision, which `constrained_mode` checks).
    - log det J from the diagonal of its Cholesky factor (potrf), which also tests that J is
      positive definite. A rejected trial costs only this.
    - With M = L_J^-1 (trtri) and C_l = M B_l M^T, the barrier's gradient is tr(J^-1 B_l) =
      tr(C_l) and its Hessian tr(J^-1 B_l J^-1 B_m) = vec(C_l) . vec(C_m). All ten C_l are two
      gemms with the ten B_l stacked (``basis_rows``), laid out so that the second one's output,
      reshaped, has the vec(C_l) as rows (``c_flat``). They do not depend on t: a new barrier
      stage at the same point reuses them.
    - The Newton system I + t C C^T (BLAS syrk) and its right-hand side v - t C vec(I) (gemv)
      are solved by one LAPACK posv (by LU, as the plain computation, should rounding make the
      Cholesky fail).
    - |v - s u|^2 = |v|^2 - 2 s v.u + s^2 u.u from dot products, once per Newton step.
    """
    lower, info = _potrf(cov, 1, 1)
    if info != 0 or not math.isfinite(_dot(lower.ravel(), lower.ravel())):
        raise np.linalg.LinAlgError("cov is not positive definite and finite")
    basis = np.dot(lower.T, _PSEUDO_INERTIA_BASIS)  # rows: B_l = d J / d v_l, flattened
    basis_T = basis.T  # Fortran-ordered (16, 10), for gemv
    # The B_l stacked, (40, 4) with rows (l, a): the gemm basis_rows M^T = [M B_0, ..., M B_9]^T
    # is written, transposed, into m_basis (4, 40) = [M B_0, ..., M B_9]. Reshaped to (40, 4)
    # that has rows (i, l) and columns a, so that M @ it^T has the entries (M B_l M^T)[i, j] =
    # C_l[i, j] at [j, 10 i + l]: c_cat reshaped to (16, 10) has vec(C_l) as column l.
    basis_rows = np.asfortranarray(basis.reshape(40, 4))
    m_basis = np.empty((4, 40))
    m_basis_T = m_basis.T
    m_basis_rows_T = m_basis.reshape(40, 4).T
    c_cat = np.empty((4, 40))
    c_cat_T = c_cat.T
    c_flat = c_cat.reshape(16, 10).T  # (10, 16), Fortran-ordered: row l is vec(C_l) permuted

    v, t = _barrier_start(mean, lower, clipped, start)
    v = v.copy()  # updated in place
    # J(v) and J(u) as flat vectors (C order; J is symmetric, so also its Fortran order).
    j_v = np.dot(mean, _PSEUDO_INERTIA_BASIS)
    _gemv(1.0, basis_T, v, 1.0, j_v, 0, 1, 0, 1, 0, 1)  # (alpha, a, x, beta, y, ..., overwrite_y)
    j_u = np.empty(16)
    # Work buffers, all written in place (the wrappers' last arguments): the Cholesky factor of a
    # trial's J, then M = L_J^-1 of the accepted one; the Newton system, its right-hand side
    # and its solution.
    j_lower = np.empty((4, 4), order="F")
    j_lower_flat = j_lower.T.ravel()
    j_lower_diag = j_lower_flat[::5]
    hess = np.empty((10, 10), order="F")
    grad = np.empty(10)
    direction = np.empty(10)
    potrf, trtri, gemm, syrk, gemv, posv = _potrf, _trtri, _gemm, _syrk, _gemv, _posv
    dot, axpy, copy, log, isfinite = _dot, _axpy, _copy, math.log, math.isfinite
    eye10, vec_eye4 = _EYE10_F, _VEC_EYE4

    copy(j_v, j_lower_flat)
    if potrf(j_lower, 1, 1, 1)[1] != 0:  # (a, lower, clean, overwrite_a)
        raise np.linalg.LinAlgError("the starting point is not strictly consistent")
    log_det = _log_det(j_lower)
    v_sq = dot(v, v)
    c_current = False  # whether c_cat holds the C_l of the current v (they do not depend on t)
    while True:
        for _ in range(50):
            if not c_current:
                if trtri(j_lower, 1, 0, 1)[1] != 0:  # M = L_J^-1 in place: (c, lower, unit, ow)
                    raise np.linalg.LinAlgError("singular pseudo-inertia factor")
                # gemm (alpha, a, b, beta, c, trans_a, trans_b, overwrite_c), each product
                # written in place as its transpose.
                gemm(1.0, basis_rows, j_lower, 0.0, m_basis_T, 0, 1, 1)
                gemm(1.0, m_basis_rows_T, j_lower, 0.0, c_cat_T, 1, 1, 1)
                c_current = True
            # I + t C C^T, lower triangle: syrk (alpha, a, beta, c, trans, lower, overwrite_c).
            hess[...] = eye10
            syrk(t, c_flat, 1.0, hess, 0, 1, 1)
            # v - t C vec(I), the gradient of the barrier problem: gemv (alpha, a, x, beta, y).
            copy(v, grad)
            gemv(-t, c_flat, vec_eye4, 1.0, grad, 0, 1, 0, 1, 0, 1)
            # H^-1 grad (the step is minus that): posv (a, b, lower, overwrite_a, overwrite_b).
            copy(grad, direction)
            if posv(hess, direction, 1, 1, 1)[2] != 0:
                # Positive definite in exact arithmetic, but rounding can break the Cholesky
                # when J is nearly singular: solve by LU, as np.linalg.solve (which raises if
                # the system is singular).
                hess_full = np.dot(c_flat, c_flat.T)
                hess_full *= t
                hess_full += np.eye(10)
                direction[...] = np.linalg.solve(hess_full, grad)
            decrement = dot(grad, direction)  # twice the predicted decrease
            if not isfinite(decrement):
                raise FloatingPointError("non-finite Newton decrement")
            if decrement < 0.1 * gap:
                break
            value = 0.5 * v_sq - t * log_det
            gemv(1.0, basis_T, direction, 0.0, j_u, 0, 1, 0, 1, 0, 1)
            v_dir = dot(v, direction)
            dir_sq = dot(direction, direction)
            scale = 1.0
            while scale > 1e-12:
                copy(j_v, j_lower_flat)
                axpy(j_u, j_lower_flat, 16, -scale)  # J(v - scale u)
                if potrf(j_lower, 1, 1, 1)[1] == 0:
                    # log det J = 2 sum log diag(L_J): the log of the product unless far from 1.
                    d0, d1, d2, d3 = j_lower_diag.tolist()
                    diag = d0 * d1 * d2 * d3
                    if 1e-280 < diag < 1e280:
                        trial_log_det = 2.0 * log(diag)
                    else:
                        trial_log_det = _log_det(j_lower)
                    trial_sq = v_sq - 2.0 * scale * v_dir + scale * scale * dir_sq
                    if 0.5 * trial_sq - t * trial_log_det <= value - 0.25 * scale * decrement:
                        break
                scale *= 0.5
            else:
                # No acceptable step (v stays): its factor is needed again.
                copy(j_v, j_lower_flat)
                potrf(j_lower, 1, 1, 1)
                c_current = False
                break
            axpy(direction, v, 10, -scale)
            axpy(j_u, j_v, 16, -scale)  # as for the trial, so J(v) is its J
            v_sq, log_det = trial_sq, trial_log_det
            c_current = False
        if 4.0 * t <= gap:
            break
        t = max(0.02 * t, 0.25 * gap)
    return mean + np.dot(lower, v)


def _barrier_mode_reference(
    mean: np.ndarray,
    cov: np.ndarray,
    clipped: np.ndarray,
    start: np.ndarray | None,
    gap: float,
) -> np.ndarray:
    """`_barrier_mode` computed plainly: J from pi, its inverse, einsums, np.linalg.solve (about
    five times slower). `constrained_mode` falls back on it when `_barrier_mode` breaks down, and
    the tests hold the two to each other."""
    lower = np.linalg.cholesky(cov)
    basis = _PSEUDO_INERTIA_BASIS.reshape(10, 4, 4)
    basis_l = np.einsum("kij,kl->lij", basis, lower)  # d J / d v_l

    def barrier_terms(pi: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
        """log det J, its gradient and (minus) Hessian in v; None where J is not definite."""
        j = params_to_pseudo_inertia(pi)
        try:
            chol = np.linalg.cholesky(j)
        except np.linalg.LinAlgError:
            return None
        a = np.einsum("ij,ljk->lik", np.linalg.inv(j), basis_l)  # J^-1 dJ/dv_l
        grad = np.einsum("lii->l", a)
        hess = np.einsum("lij,mji->lm", a, a)
        return 2.0 * float(np.log(np.diag(chol)).sum()), grad, hess

    v, t = _barrier_start(mean, lower, clipped, start)
    terms = barrier_terms(mean + lower @ v)
    if terms is None:
        raise np.linalg.LinAlgError("the starting point is not strictly consistent")
    while True:
        for _ in range(50):
            logdet, grad_b, hess_b = terms
            grad = v - t * grad_b
            step = -np.linalg.solve(np.eye(10) + t * hess_b, grad)
            decrement = -float(grad @ step)  # twice the predicted decrease
            if decrement < 0.1 * gap:
                break
            value = 0.5 * float(v @ v) - t * logdet
            scale = 1.0
            while scale > 1e-12:
                trial = v + scale * step
                trial_terms = barrier_terms(mean + lower @ trial)
                if trial_terms is not None:
                    trial_value = 0.5 * float(trial @ trial) - t * trial_terms[0]
                    if trial_value <= value - 0.25 * scale * decrement:
                        break
                scale *= 0.5
            else:
                break
            v, terms = trial, trial_terms
        if 4.0 * t <= gap:
            break
        t = max(0.02 * t, 0.25 * gap)
    return mean + lower @ v


def _log_det(lower: np.ndarray) -> float:
    """log det J = 2 sum log diag(L) from the (4, 4) Cholesky factor L of J; a
    FloatingPointError if not finite (a NaN passes OpenBLAS's potrf)."""
    log_det = 2.0 * sum(math.log(lower.item(k)) for k in (0, 5, 10, 15))
    if not math.isfinite(log_det):
        raise FloatingPointError("non-finite log det J")
    return log_det


class InertialParamUKF(BatchedUKF):
    """UKF on a rigid body's 10 standard inertial parameters pi, reporting consistent bodies.

    State x = pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m, kg m^2;
    h = m c, I about the frame origin), constant with a small random walk. Measurements
    z = A pi + b + v (the wrench balance, ``estimator.rne``) are linear in pi, so the unscented
    transform is exact and this filter is the Kalman filter of the linear-Gaussian model: its
    posterior N(x, P) is the exact posterior of its Gaussian prior and measurements (the tests
    hold it to a linear Kalman filter and to filterpy's stock UKF).

    Physical consistency (constrained filtering): the true body lies in the convex set of bodies
    with a positive semidefinite pseudo-inertia J. The posterior restricted to that set is N(x, P)
    truncated to it; what the filter reports (`params_mean`) is its mode, the consistent body of
    highest density (`constrained_mode`): x itself whenever x is consistent, else the Mahalanobis
    projection of x on the set. Every reported estimate is therefore a realisable body; x itself
    may leave the set while the data leave directions unseen (its sigma points then need not be
    consistent, which is harmless as the measurement function is linear and defined for any pi).

    Why not filter in log-Cholesky coordinates (`LogCholeskyUKF`) as DESIGN.md recommends: pi(eta)
    is strongly nonlinear, and on the wrench-balance data the unscented update in eta collapses the
    covariance along directions the data have not yet pinned down while the mean is still off. On
    recordings of 90 s nominal two-robot runs with weak roll excitation its final NEES (10
    parameters) was 1.8e3 to 5.4e4 with principal moments off by 30 to 48 %, while this filter,
    on the very same measurements, ended with NEES 11 and the errors of batch weighted least
    squares. On the benchmark's scenarios (scripts/benchmark_estimation.py replays every case's
    measurements through both) its mean NEES is 9 to 79 against 2.5 to 12, and its worst
    principal-moment error on the two-robot tumble 35 % against 22 %. Projection is acceptable
    "only if measured to be no worse": it is better.

    Args:
        prior_params: prior mean pi (10,), physically consistent.
        prior_cov: prior covariance of pi (10, 10) (``estimator.cargo_estimator.prior_covariance``
            builds it from standard deviations of mass, centre of mass and inertia).
        process_cov: random-walk covariance of pi per `predict` (10, 10).
        dim_z, alpha, beta, kappa, gate_nis: as for `BatchedUKF`.
    """

    def __init__(
        self,
        prior_params: np.ndarray,
        prior_cov: np.ndarray,
        process_cov: np.ndarray,
        dim_z: int = 6,
        alpha: float = DEFAULT_ALPHA,
        beta: float = DEFAULT_BETA,
        kappa: float = DEFAULT_KAPPA,
        gate_nis: float | None = None,
    ) -> None:
        prior_params = _checked_prior(prior_params)
        violation = physical_violation(prior_params)
        if violation is not None:
            raise ValueError(f"prior_params must be a physically consistent body: {violation}")
        super().__init__(
            N_INERTIAL_PARAMS,
            dim_z,
            prior_params,
            prior_cov,
            process_cov,
            alpha=alpha,
            beta=beta,
            kappa=kappa,
            gate_nis=gate_nis,
        )
        self._mode_x = np.full(N_INERTIAL_PARAMS, np.nan)
        self._mode_P = np.full((N_INERTIAL_PARAMS, N_INERTIAL_PARAMS), np.nan)
        self._mode = prior_params.copy()
        self.n_mode_fallbacks = 0  # reports that fell back to the eigenvalue-clipped body

    def update_linear(
        self, z: np.ndarray, A: np.ndarray, b: np.ndarray, R: np.ndarray
    ) -> UpdateResult:
        """Fuse z = A pi + b + v, v ~ N(0, R), with A (m, 10), b (m,), R (m, m)."""
        return self.update(z, _checked_linear_hx(A, b, self.dim_z, False), R)

    def _refresh_mode(self) -> None:
        if np.array_equal(self.x, self._mode_x) and np.array_equal(self.P, self._mode_P):
            return
        self._mode, solved = constrained_mode(self.x, self.P, start=self._mode)
        self.n_mode_fallbacks += not solved
        self._mode_x = self.x.copy()
        self._mode_P = self.P.copy()

    def params_mean(self) -> np.ndarray:
        """The reported estimate: the physically consistent body of highest posterior density
        (x when x is consistent); a copy."""
        self._refresh_mode()
        return self._mode.copy()

    def params_cov(self) -> np.ndarray:
        """Posterior covariance of pi (10, 10), a copy of P."""
        return self.P.copy()

    def params_std(self) -> np.ndarray:
        """Posterior standard deviations (10,) of pi."""
        return np.sqrt(np.diag(self.P))

    def physical_estimate(self, step: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation of [m, c (3), I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, m,
        kg m^2; inertia about the centre of mass): the values of the reported body, and the
        standard deviations of the posterior carried through the map's Jacobian at that body
        (central differences, one vectorised call)."""
        mode = self.params_mean()
        probes = np.vstack((mode, mode + step * np.eye(10), mode - step * np.eye(10)))
        mass, com, inertia = mass_com_inertia_from_params(probes)
        values = np.concatenate(
            (mass[:, None], com, inertia[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]), axis=1
        )
        jac = (values[1:11] - values[11:21]).T / (2.0 * step)
        var = np.einsum("ij,jk,ik->i", jac, self.P, jac)
        return values[0], np.sqrt(np.maximum(var, 0.0))
