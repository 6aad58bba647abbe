"""Unscented Kalman filters on a rigid body's inertial parameters, as in filterpy's UKF.py.

Parameters and frames. `InertialParamUKF` filters the ten standard inertial parameters
pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m, kg m^2; h = m c with c the
centre of mass, I the inertia about the origin of the body frame the measurements are expressed
in: the grasp frame, for the cargo estimator). The measurement, the wrench balance z = A pi + b
(``estimator.rne``; z and b in N and N m), is linear in pi.

Model. The state is constant up to a random walk, x_(k+1) = x_k + w, w ~ N(0, Q) (Q = 0 for a
rigid cargo, the cargo estimator's default), and a measurement is z = h(x) + v, v ~ N(0, R).
One step is filterpy's: sigma points -> unscented transform -> gain (``estimator.unscented``
holds the compiled pieces).

Merwe scaled sigma points (filterpy's `MerweScaledSigmaPoints`; its weights are used as they are)
for n states and parameters alpha, beta, kappa:

    lambda = alpha^2 (n + kappa) - n,   P = L L^T (lower Cholesky factor)
    X_0 = x,   X_(1+k) = x + sqrt(n + lambda) L[:, k],   X_(1+n+k) = x - sqrt(n + lambda) L[:, k]
    Wm_0 = lambda / (n + lambda),   Wc_0 = Wm_0 + 1 - alpha^2 + beta,
    Wm_i = Wc_i = 1 / (2 (n + lambda))   (i = 1 .. 2n)

Predict. Through the identity map the unscented transform of the sigma points is exactly (x, P),
so `predict` is its closed form: x unchanged, P <- P + Q (filterpy's route gives the same to
rounding, then redraws the sigma points from the predicted (x, P), which `update` does too).

Update (filterpy's `unscented_transform` and `UnscentedKalmanFilter.update`), Z_i = h(X_i):

    z_pred = sum_i Wm_i Z_i,    S = sum_i Wc_i (Z_i - z_pred)(Z_i - z_pred)^T + R
    P_xz = sum_i Wc_i (X_i - x)(Z_i - z_pred)^T
    K = P_xz S^-1,    y = z - z_pred,    NIS = y^T S^-1 y
    x <- x + K y,     P <- P - K S K^T   (the standard form, symmetrised)

S^-1 is applied through the Cholesky factor S = L_S L_S^T: with W = L_S^-1 P_zx and w = L_S^-1 y,
K y = W^T w, K S K^T = W^T W and NIS = w.w. Log-likelihood = -0.5 (NIS + log det S + m log 2 pi).
Because the measurement of `InertialParamUKF` is linear, the unscented transform is exact and
the filter equals the linear Kalman filter of that model (the tests hold it to a closed-form
Kalman filter and to filterpy's stock UnscentedKalmanFilter).

Beyond filterpy: inputs are shape-checked (ValueError naming the expected shape); an update with
NaN or inf in z, R or h(X) is skipped and counted; one whose P, S or posterior P is not positive
definite is rejected and counted; one with NIS above ``gate_nis`` is rejected and counted. A
skipped or rejected update leaves x and P as they were.

Physical consistency (``estimator.constrained``). What `InertialParamUKF` reports is the body of
highest posterior density among the realisable ones, those with a positive definite pseudo-inertia
J(pi) = [[0.5 tr(I) 1 - I, h], [h^T, m]]: with P = L L^T and pi = x + L v, minimise 0.5 |v|^2
subject to J(x + L v) > 0, by Newton steps on the log-det barrier 0.5 |v|^2 - t log det J for
decreasing t (the objective, constraint and Newton step are spelled out there).

`LogCholeskyUKF` filters log-Cholesky coordinates instead; it is kept as the measured reference
for that choice (see its docstring).

Speed: an update is one compiled call (`update_linear`) or two around the Python measurement
function (`update`), on a filter whose arrays live in one buffer updated in place; `predict` only
marks the addition of Q, which the next update's compiled call makes first (or reading P does).
Run with OPENBLAS_NUM_THREADS=1: BLAS threads only slow matrices this small.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints
from filterpy.kalman import unscented_transform as filterpy_unscented_transform

from . import unscented
from .constrained import cholesky_lower, constrained_mode
from .copies import deepcopy_state
from .inertia import (
    log_cholesky_to_params,
    mass_com_inertia_from_params,
    params_to_log_cholesky,
    physical_violation,
)
from .unscented import merwe_sigma_points, unscented_transform

__all__ = [
    "BatchedUKF",
    "InertialParamUKF",
    "LogCholeskyUKF",
    "UpdateResult",
    "constrained_mode",
    "linear_params_hx",
    "merwe_sigma_points",
    "unscented_transform",
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

# Per outcome of ``estimator.unscented`` (in the order of its codes): reason and counter.
_OUTCOMES = (
    ("ok", "n_updates"),
    ("non-finite", "n_skipped_nonfinite"),  # R
    ("not-positive-definite", "n_rejected_not_pd"),  # P
    ("non-finite", "n_skipped_nonfinite"),  # h(X)
    ("not-positive-definite", "n_rejected_not_pd"),  # S
    ("non-finite", "n_skipped_nonfinite"),  # z
    ("not-positive-definite", "n_rejected_not_pd"),  # NIS not finite with finite inputs
    ("gated", "n_gated"),
    ("not-positive-definite", "n_rejected_not_pd"),  # posterior P
)


class UpdateResult(NamedTuple):
    """Outcome of one measurement update.

    accepted: whether x and P were changed.
    reason: "ok", "non-finite" (NaN/inf in z, R or the hx output), "gated" (NIS above the gate)
        or "not-positive-definite" (P, S or the posterior P failed its Cholesky).
    nis: normalised innovation squared y^T S^-1 y (NaN when it could not be computed).
    """

    accepted: bool
    reason: str
    nis: float


# NamedTuple's own __new__ is a Python function; tuple.__new__ builds the same object faster.
_new_tuple = tuple.__new__


def _as_float_array(value: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    """`value` as a C-contiguous float64 array of the given shape; ValueError naming it."""
    array = np.ascontiguousarray(value, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


def linear_params_hx(
    A: np.ndarray,
    b: np.ndarray,
    to_params: Callable[[np.ndarray], np.ndarray] | None = log_cholesky_to_params,
) -> Callable[[np.ndarray], np.ndarray]:
    """Batched measurement function of z = A pi(x) + b: sigma points (k, 10) -> (k, m).

    A is (m, 10) and b (m,); pi(x) is ``to_params`` (`log_cholesky_to_params` for the state of
    `LogCholeskyUKF`; None when the state is pi itself, as in `InertialParamUKF`).
    """
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)

    def hx_batch(sigmas: np.ndarray) -> np.ndarray:
        params = sigmas if to_params is None else to_params(sigmas)
        return params @ A.T + b

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

    Attributes: x, P, Q (mean, covariance, process noise: the filter's own arrays, updated in
    place, so copy them to keep a value; assigning copies into them); y, S, P_xz, K, nis,
    log_likelihood (innovation, its covariance, the cross-covariance, the gain, the NIS and the
    Gaussian log-likelihood of the last update that got that far, gated or not); sigmas,
    sigmas_h (the last sigma points and their images); counters n_updates (accepted),
    n_skipped_nonfinite, n_gated, n_rejected_not_pd; points (the filterpy sigma-point object),
    Wm, Wc (its weights).
    """

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

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
        n, m = self.dim_x, self.dim_z = int(dim_x), int(dim_z)
        lambda_ = alpha**2 * (n + kappa) - n
        if not n + lambda_ > 0.0:
            raise ValueError(
                f"alpha^2 (n + kappa) must be positive, got alpha={alpha}, kappa={kappa}"
            )
        self.points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
        self.n_sigma = 2 * n + 1
        x0 = _as_float_array(x0, (n,), "x0")
        P0 = _as_float_array(P0, (n, n), "P0")
        if not (np.isfinite(x0).all() and np.isfinite(P0).all()):
            raise ValueError("x0 and P0 must be finite")
        P0 = 0.5 * (P0 + P0.T)
        if not cholesky_lower(P0)[1]:
            raise ValueError("P0 must be symmetric positive definite")

        # The filter's arrays live in one buffer that the compiled kernels update in place
        # (`unscented.filter_arrays`); the attributes are views of it.
        self._state = np.zeros(unscented.state_size(n, m))
        self._bind_views()
        self._x[:], self._P[:], self._Q[:] = x0, P0, self._checked_Q(Q)
        self.Wm[:], self.Wc[:] = self.points.Wm, self.points.Wc
        self._scalars[:] = (math.sqrt(n + lambda_), math.inf, math.nan, -math.inf)
        self.gate_nis = gate_nis
        self._predict_pending = False  # a `predict` whose P += Q is not yet made
        self.n_updates = 0
        self.n_skipped_nonfinite = 0
        self.n_gated = 0
        self.n_rejected_not_pd = 0

    _VIEWS = ("_x", "_P", "_Q", "sigmas", "sigmas_h", "y", "S", "P_xz", "Wm", "Wc", "_scalars")

    def _bind_views(self) -> None:
        arrays = unscented.filter_arrays(self._state, self.dim_x, self.dim_z)
        for name, array in zip(self._VIEWS, arrays, strict=True):
            setattr(self, name, array)

    def __getstate__(self) -> dict:
        # A copy (pickle, deepcopy) would give each view its own memory, detached from the
        # buffer the kernels update: copy the buffer alone and take the views again.
        return {k: v for k, v in self.__dict__.items() if k not in self._VIEWS}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._bind_views()

    def _checked_Q(self, Q: np.ndarray) -> np.ndarray:
        Q = _as_float_array(Q, (self.dim_x, self.dim_x), "Q")
        if not np.isfinite(Q).all():
            raise ValueError("Q must be finite")
        return 0.5 * (Q + Q.T)  # a symmetric Q keeps P exactly symmetric through predict

    @property
    def x(self) -> np.ndarray:
        """Mean (n,)."""
        return self._x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        self._x[:] = _as_float_array(value, (self.dim_x,), "x")

    @property
    def P(self) -> np.ndarray:
        """Covariance (n, n), after every `predict` made so far."""
        if self._predict_pending:
            self._P += self._Q
            self._predict_pending = False
        return self._P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self._P[:] = _as_float_array(value, (self.dim_x, self.dim_x), "P")
        self._predict_pending = False

    @property
    def Q(self) -> np.ndarray:
        """Process noise covariance per `predict` (n, n), symmetric."""
        return self._Q

    @Q.setter
    def Q(self, value: np.ndarray) -> None:
        self.P  # noqa: B018 (a pending predict adds the old Q)
        self._Q[:] = self._checked_Q(value)

    @property
    def gate_nis(self) -> float | None:
        """NIS above which an update is rejected (None: no gating)."""
        gate = float(self._scalars[1])
        return None if gate == math.inf else gate

    @gate_nis.setter
    def gate_nis(self, value: float | None) -> None:
        if value is not None and not value > 0.0:
            raise ValueError(f"gate_nis must be positive or None, got {value}")
        self._scalars[1] = math.inf if value is None else float(value)

    @property
    def nis(self) -> float:
        """NIS of the last update that computed one (NaN before any)."""
        return float(self._scalars[2])

    @property
    def log_likelihood(self) -> float:
        """Gaussian log-likelihood of the last innovation y under N(0, S) (-inf before any)."""
        return float(self._scalars[3])

    @property
    def K(self) -> np.ndarray:
        """Kalman gain P_xz S^-1 (n, m) of the last update that computed an innovation."""
        if not self.S.any():
            return np.zeros((self.dim_x, self.dim_z))
        return np.linalg.solve(self.S, self.P_xz.T).T

    def sigma_points(self) -> np.ndarray:
        """Merwe sigma points of the current (x, P), shape (2n + 1, n), filterpy's ordering.

        Raises np.linalg.LinAlgError if P is not positive definite.
        """
        sigmas, definite = merwe_sigma_points(self.x, self.P, self._scalars[0])
        if not definite:
            raise np.linalg.LinAlgError("P is not positive definite")
        return sigmas

    def predict(self, Q: np.ndarray | None = None) -> None:
        """Propagate through x_(k+1) = x_k + w: x is unchanged, P grows by Q (or by `self.Q`):
        the unscented transform of the identity map in closed form. With the filter's own Q the
        addition is made by the next update's compiled call (or when P is read)."""
        if Q is not None:
            self.P += self._checked_Q(Q)
            return
        if self._predict_pending:  # the previous predict first: P + Q + Q, in that order
            self._P += self._Q
        self._predict_pending = True

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
        n, m = self.dim_x, self.dim_z
        z, R = _as_float_array(z, (m,), "z"), _as_float_array(R, (m, m), "R")
        outcome, sigmas = unscented.draw_sigma_points(self._state, n, m, R, self._predict_pending)
        self._predict_pending = False
        if outcome != unscented.OK:
            return self._result(outcome, math.nan)
        sigmas_h = np.asarray(hx_batch(sigmas), dtype=float)
        if sigmas_h.shape != (self.n_sigma, m):
            raise ValueError(
                f"hx_batch must return shape ({self.n_sigma}, {m}) for sigma points of "
                f"shape {sigmas.shape}, got {sigmas_h.shape}"
            )
        sigmas_h = np.ascontiguousarray(sigmas_h)
        return self._result(*unscented.update_from_images(self._state, n, m, sigmas_h, z, R))

    def _result(self, outcome: int, nis: float) -> UpdateResult:
        """Count an update's outcome and say what it was."""
        if outcome == unscented.OK:
            self.n_updates += 1
            return _new_tuple(UpdateResult, (True, "ok", nis))
        reason, counter = _OUTCOMES[outcome]
        setattr(self, counter, getattr(self, counter) + 1)
        return UpdateResult(False, reason, nis)


class InertialParamUKF(BatchedUKF):
    """UKF on a rigid body's 10 standard inertial parameters pi, reporting consistent bodies.

    State x = pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m, kg m^2;
    h = m c, I about the frame origin), constant up to the random walk Q. Measurements
    z = A pi + b + v (the wrench balance, ``estimator.rne``) are linear in pi, so the unscented
    transform is exact and this filter is the Kalman filter of the linear-Gaussian model: its
    posterior N(x, P) is the exact posterior of its Gaussian prior and measurements (the tests
    hold it to a linear Kalman filter and to filterpy's stock UKF).

    Physical consistency: the true body lies in the convex set of bodies with a positive
    semidefinite pseudo-inertia J. What the filter reports (`params_mean`) is the mode of N(x, P)
    restricted to that set, the consistent body of highest density (`constrained_mode`): x itself
    whenever x is consistent, else the Mahalanobis projection of x on the set. x itself may leave
    the set while the data leave directions unseen, which is harmless as the measurement is
    linear and defined for any pi.

    Why not filter in log-Cholesky coordinates (`LogCholeskyUKF`): pi(eta) is strongly
    nonlinear, and on the wrench-balance data the unscented update in eta collapses the
    covariance along directions the data have not yet pinned down while the mean is still off.
    On the benchmark's scenarios (scripts/benchmark_estimation.py replays every case's
    measurements through both) its mean NEES is 9 to 79 against 2.5 to 12 here, and its worst
    principal-moment error on the two-robot tumble 35 % against 22 %.

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
        prior_params = _as_float_array(prior_params, (N_INERTIAL_PARAMS,), "prior_params")
        violation = physical_violation(prior_params)
        if violation is not None:
            raise ValueError(f"prior_params must be a physically consistent body: {violation}")
        super().__init__(
            N_INERTIAL_PARAMS, dim_z, prior_params, prior_cov, process_cov,
            alpha=alpha, beta=beta, kappa=kappa, gate_nis=gate_nis,
        )  # fmt: skip
        self._mode_of: np.ndarray | None = None  # the (x, P) of `_mode`, as `_moments` holds them
        self._mode = prior_params.copy()
        self.n_mode_fallbacks = 0  # reports that fell back to the eigenvalue-clipped body

    def update_linear(
        self, z: np.ndarray, A: np.ndarray, b: np.ndarray, R: np.ndarray
    ) -> UpdateResult:
        """Fuse z = A pi + b + v, v ~ N(0, R), with A (m, 10), b (m,), R (m, m)."""
        n, m = self.dim_x, self.dim_z
        try:
            outcome, nis = unscented.update_linear(
                self._state, n, m, z, A, b, R, self._predict_pending
            )
        except TypeError:  # not C-contiguous float64 arrays: convert them, checking shapes
            z, A, b, R = self._checked_linear_inputs(z, A, b, R)
            outcome, nis = unscented.update_linear(
                self._state, n, m, z, A, b, R, self._predict_pending
            )
        if outcome == unscented.BAD_SHAPE:  # nothing was done
            self._checked_linear_inputs(z, A, b, R)  # raises the ValueError that names it
        self._predict_pending = False
        if outcome == unscented.OK:  # `_result`, inline on the common path
            self.n_updates += 1
            return _new_tuple(UpdateResult, (True, "ok", nis))
        return self._result(outcome, nis)

    def _checked_linear_inputs(self, z, A, b, R) -> tuple[np.ndarray, ...]:
        m = self.dim_z
        return (
            _as_float_array(z, (m,), "z"),
            _as_float_array(A, (m, N_INERTIAL_PARAMS), "A"),
            _as_float_array(b, (m,), "b"),
            _as_float_array(R, (m, m), "R"),
        )

    def params_mean(self, offset: np.ndarray | None = None) -> np.ndarray:
        """The reported estimate: the physically consistent body of highest posterior density
        (x when x is consistent); a copy. ``offset`` (10,): that of N(x + offset, P) (the
        deferred bias compensation, ``estimator.bias_compensation``; not cached)."""
        if offset is not None:
            return constrained_mode(self.x + offset, self.P, start=self._mode)[0]
        moments = self._moments()
        if not unscented.same_values(moments, self._mode_of):
            self._mode, solved = constrained_mode(self._x, self._P, start=self._mode)
            self.n_mode_fallbacks += not solved
            self._mode_of = moments.copy()
        return self._mode.copy()

    def _moments(self) -> np.ndarray:
        """x and P, after every `predict`, as one flat view of the buffer (x's row, then P's:
        `unscented.filter_arrays`), so that one comparison tells whether either changed."""
        self.P  # noqa: B018 (a pending predict adds Q)
        n = self.dim_x
        return self._state[: n * (n + 1)]

    def params_cov(self) -> np.ndarray:
        """Posterior covariance of pi (10, 10), a copy of P."""
        return self.P.copy()

    def params_std(self) -> np.ndarray:
        """Posterior standard deviations (10,) of pi."""
        return np.sqrt(np.diag(self.P))

    def physical_estimate(
        self, step: float = 1e-6, offset: np.ndarray | None = None, cov: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation of [m, c (3), I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, m,
        kg m^2; inertia about the centre of mass): the values of the reported body
        (``params_mean(offset)``), and the standard deviations of the posterior carried through
        the map's Jacobian at that body (central differences, one vectorised call); ``cov`` in
        place of P where given."""
        mode = self.params_mean(offset)
        probes = np.vstack((mode, mode + step * np.eye(10), mode - step * np.eye(10)))
        mass, com, inertia = mass_com_inertia_from_params(probes)
        values = np.concatenate(
            (mass[:, None], com, inertia[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]), axis=1
        )
        jac = (values[1:11] - values[11:21]).T / (2.0 * step)
        var = np.einsum("ij,jk,ik->i", jac, self.P if cov is None else cov, jac)
        return values[0], np.sqrt(np.maximum(var, 0.0))


# Prior standard deviations for `LogCholeskyUKF` in log-Cholesky coordinates (alpha, d1..3, s12,
# s23, s13, t1..3): mass within a factor ~e^(2*0.5) = 2.7, principal second moments within a
# factor ~e^2, centre of mass within 0.15 m (what CargoEstimator used with it).
LOG_CHOLESKY_PRIOR_STD = np.array([0.5, 1.0, 1.0, 1.0, 0.3, 0.3, 0.3, 0.15, 0.15, 0.15])
LOG_CHOLESKY_PROCESS_STD = 1e-5


class LogCholeskyUKF(BatchedUKF):
    """UKF on a rigid body's inertial parameters, filtered in log-Cholesky coordinates eta.

    The state x is eta (10,); every sigma point maps to a physically realisable body through
    `log_cholesky_to_params`. Parameters are reported in standard form pi (as `InertialParamUKF`).

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
    NIS gating. Measured against `InertialParamUKF` on the same data, it is worse (see there).
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
        prior_params = _as_float_array(prior_params, (N_INERTIAL_PARAMS,), "prior_params")
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
        A = _as_float_array(A, (self.dim_z, N_INERTIAL_PARAMS), "A")
        b = _as_float_array(b, (self.dim_z,), "b")
        return self.update(z, linear_params_hx(A, b, log_cholesky_to_params), R)

    def params_mean(self) -> np.ndarray:
        """Standard parameters pi(eta_mean) of the mean state.

        Chosen over the unscented mean of pi because pi(eta_mean) is always a realisable body,
        while a weighted mean with a negative Wm0 need not be.
        """
        return log_cholesky_to_params(self.x)

    def params_cov(self) -> np.ndarray:
        """Covariance (10, 10) of pi: unscented transform of the sigma points of (eta, P)."""
        params_sigmas = log_cholesky_to_params(self.sigma_points())
        _, cov = filterpy_unscented_transform(params_sigmas, self.Wm, self.Wc)
        return 0.5 * (cov + cov.T)

    def params_std(self) -> np.ndarray:
        """Standard deviations (10,) of pi from `params_cov` (negative rounding clipped to 0)."""
        return np.sqrt(np.maximum(np.diag(self.params_cov()), 0.0))
