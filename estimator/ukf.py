"""Unscented Kalman filters with batched measurement functions.

`BatchedUKF` is an additive-noise UKF for a *constant* state (x_{k+1} = x_k + w, w ~ N(0, Q)) whose
measurement function maps all sigma points at once, ``hx_batch(sigmas (n_sigma, n)) -> (n_sigma,
m)``. Sigma points and weights come from filterpy's `MerweScaledSigmaPoints` and the predicted
measurement from filterpy's `unscented_transform`, so a step reproduces filterpy 2.0's stock
`UnscentedKalmanFilter` (fx = identity, the same points object, Q and R) to rounding, while
skipping its per-sigma-point Python loops.

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
- The gain, innovation and posterior are filterpy's: K = Pxz S^-1, x += K y, P -= K S K^T.

Additions over filterpy: inputs are shape-checked (ValueError naming the expected shape); an update
with a non-finite z, R or hx output is skipped and counted; the posterior P is symmetrised and
Cholesky-checked, and an update whose posterior is not positive definite is rejected (x and P keep
their prior values) and counted; an innovation whose NIS exceeds ``gate_nis`` is rejected and
counted.

`InertialParamUKF` filters a rigid body's 10 inertial parameters in log-Cholesky coordinates eta
(see `estimator.inertia`), so every sigma point is a physically realisable body without clipping
or projection; measurements linear in the standard parameters pi enter through `update_linear`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, unscented_transform
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dpotrs as _potrs

from .inertia import log_cholesky_to_params, params_to_log_cholesky

__all__ = ["BatchedUKF", "InertialParamUKF", "UpdateResult"]

# Default Merwe parameters. With n = 10, alpha = 0.5 and kappa = 0 give lambda = -7.5, a spread of
# sqrt(n + lambda) = 1.58 standard deviations per axis, Wm0 = -3 and Wc0 = -0.25. kappa = 3 - n
# would give Wm0 = -12.3 and Wc0 = -9.6 (the huge negative weights that make the transformed
# covariance indefinite), and alpha = 1 spreads the points 3.2 standard deviations out, far into
# the nonlinearity of exp() in the log-Cholesky map.
DEFAULT_ALPHA = 0.5
DEFAULT_BETA = 2.0
DEFAULT_KAPPA = 0.0

N_INERTIAL_PARAMS = 10


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
    return bool(np.isfinite(array).all())


def _cholesky_lower(matrix: np.ndarray) -> tuple[np.ndarray, int]:
    """Lower Cholesky factor via LAPACK potrf (a quarter of np.linalg.cholesky's call overhead
    at n = 10); info != 0 when the matrix is not positive definite. Reads the lower triangle."""
    return _potrf(matrix, lower=1, clean=1)


def _cholesky_solve(lower: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
    """Solve (L L^T) X = rhs for a lower Cholesky factor L (LAPACK potrs)."""
    return _potrs(lower, rhs, lower=1)


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

    Attributes: x, P (current mean and covariance); y, S, K, nis (innovation, its covariance, the
    gain and the NIS of the last update that got that far); sigmas, sigmas_h (the last sigma points
    and their images); counters n_updates (accepted), n_skipped_nonfinite, n_gated,
    n_rejected_not_pd; points (the filterpy sigma-point object), Wm, Wc (its weights).
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
        # Cross-covariance sum_i Wc_i (X_i - x)(Z_i - z_pred)^T: X_0 - x = 0 and the X_i - x = +-
        # sqrt(n + lambda) L columns share one weight, so it is this factor times L (Z_+ - Z_-).
        self._cross_scale = float(self.Wc[1]) * sigma_scale
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
        self.K = np.zeros((self.dim_x, self.dim_z))
        self.nis = math.nan
        self.sigmas = np.zeros((self.n_sigma, self.dim_x))
        self.sigmas_h = np.zeros((self.n_sigma, self.dim_z))
        self.n_updates = 0
        self.n_skipped_nonfinite = 0
        self.n_gated = 0
        self.n_rejected_not_pd = 0

    def _checked_Q(self, Q: np.ndarray) -> np.ndarray:
        Q = _as_square_matrix(Q, self.dim_x, "Q")
        if not _all_finite(Q):
            raise ValueError("Q must be finite")
        return Q

    def sigma_points(self) -> np.ndarray:
        """Merwe sigma points of the current (x, P), shape (2n + 1, n), filterpy's ordering.

        Raises np.linalg.LinAlgError if P is not positive definite.
        """
        lower, info = _cholesky_lower(self.P)
        if info != 0:
            raise np.linalg.LinAlgError("P is not positive definite")
        return self.x + self._sigma_offsets @ lower.T

    def predict(self, Q: np.ndarray | None = None) -> None:
        """Propagate through x_{k+1} = x_k + w: x is unchanged, P grows by Q (or by `self.Q`).

        This is the unscented transform of the identity map in closed form (see the module
        docstring).
        """
        Q = self.Q if Q is None else self._checked_Q(Q)
        self.P = self.P + Q

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
        R = _as_square_matrix(R, m, "R")
        if not (_all_finite(z) and _all_finite(R)):
            self.n_skipped_nonfinite += 1
            return UpdateResult(False, "non-finite", math.nan)

        P_lower, info = _cholesky_lower(self.P)
        if info != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", math.nan)
        sigmas = self.x + self._sigma_offsets @ P_lower.T
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

        z_pred, S = unscented_transform(sigmas_h, self.Wm, self.Wc, R)
        n = self.dim_x
        # Right-hand sides [y, P_zx] solved against S together; P_zx = P_xz^T (see __init__).
        rhs = np.empty((m, n + 1))
        y = np.subtract(z, z_pred, out=rhs[:, 0])
        P_zx = np.multiply(
            (sigmas_h[1 : n + 1] - sigmas_h[n + 1 :]).T @ P_lower.T,
            self._cross_scale,
            out=rhs[:, 1:],
        )
        # The Cholesky of S also checks it is positive definite (a negative Wc0 can make it
        # indefinite).
        S_lower, info = _cholesky_lower(S)
        if info != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", math.nan)
        solved, info = _cholesky_solve(S_lower, rhs)
        S_inv_y, K_T = solved[:, 0], solved[:, 1:]  # K = P_xz S^-1
        nis = float(y @ S_inv_y)
        self.y, self.S, self.nis = y, S, nis
        if info != 0 or not math.isfinite(nis):
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", nis)
        if self.gate_nis is not None and nis > self.gate_nis:
            self.n_gated += 1
            return UpdateResult(False, "gated", nis)

        # filterpy's P - K S K^T = P - P_xz S^-1 P_zx, and K y.
        P_post = self.P - P_zx.T @ K_T
        P_post = 0.5 * (P_post + P_post.T)
        _, info = _cholesky_lower(P_post)
        if info != 0:
            self.n_rejected_not_pd += 1
            return UpdateResult(False, "not-positive-definite", nis)
        self.K = K_T.T
        self.x = self.x + y @ K_T
        self.P = P_post
        self.n_updates += 1
        return UpdateResult(True, "ok", nis)

    @property
    def log_likelihood(self) -> float:
        """Gaussian log-likelihood of the last innovation y under N(0, S)."""
        sign, logdet = np.linalg.slogdet(2.0 * math.pi * self.S)
        if sign <= 0 or not math.isfinite(self.nis):
            return -math.inf
        return -0.5 * (self.nis + logdet)


class InertialParamUKF(BatchedUKF):
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
        prior_params = np.asarray(prior_params, dtype=float)
        if prior_params.shape != (N_INERTIAL_PARAMS,):
            raise ValueError(
                f"prior_params must have shape ({N_INERTIAL_PARAMS},), got {prior_params.shape}"
            )
        eta0 = params_to_log_cholesky(prior_params)
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
        m = self.dim_z
        A = np.asarray(A, dtype=float)
        b = np.asarray(b, dtype=float)
        if A.shape != (m, N_INERTIAL_PARAMS):
            raise ValueError(f"A must have shape ({m}, {N_INERTIAL_PARAMS}), got {A.shape}")
        if b.shape != (m,):
            raise ValueError(f"b must have shape ({m},), got {b.shape}")
        # A non-finite A or b makes the hx output non-finite, which `update` checks and counts.
        A_T = A.T

        def hx_batch(sigmas: np.ndarray) -> np.ndarray:
            return log_cholesky_to_params(sigmas) @ A_T + b

        return self.update(z, hx_batch, R)

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
