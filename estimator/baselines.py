"""The best possible next to the filter: batch weighted least squares and the Cramer-Rao bound.

Both work on the very measurements the filter used (``CargoEstimator(record=True)`` keeps them):
per update k, z_k = A_k pi + b_k + e_k with e_k ~ N(0, R_k) (``rne``: the wrench balance is linear
in the cargo's standard parameters pi). Then:

- Fisher information F = sum_k A_k^T R_k^-1 A_k; any unbiased estimator has Cov(pi) >= F^-1,
  and with the filter's Gaussian prior P0 the Bayesian bound is (P0^-1 + F)^-1.
- Weighted least squares pi = F^-1 sum_k A_k^T R_k^-1 (z_k - b_k) attains F^-1 when A_k is exact;
  it need not be physically consistent, so ``inertia.project_physical`` maps it to the nearest
  body with a positive definite pseudo-inertia (eigenvalues of J clipped).
- Bounds on derived quantities g(pi) (mass, centre of mass, principal moments) are G F^-1 G^T with
  G = dg/dpi (central differences); directions in the null space of F cannot be learned from the
  data at all, and ``unobservable_directions`` names them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .inertia import (
    mass_com_inertia_from_params,
    principal_moments,
)

PARAM_NAMES = ("m", "h_x", "h_y", "h_z", "I_xx", "I_yy", "I_zz", "I_xy", "I_xz", "I_yz")


@dataclass(frozen=True)
class Recording:
    """Stacked measurements: z (K, 6), A (K, 6, 10), b (K, 6), R (K, 6, 6)."""

    z: np.ndarray
    A: np.ndarray
    b: np.ndarray
    R: np.ndarray

    @classmethod
    def from_log(cls, log: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]):
        if not log:
            raise ValueError("the recording is empty: no update was made")
        z, a, b, r = (np.stack(x) for x in zip(*log, strict=True))
        return cls(z, a, b, r)


def fisher_information(rec: Recording) -> np.ndarray:
    """F = sum_k A_k^T R_k^-1 A_k (10, 10)."""
    r_inv_a = np.linalg.solve(rec.R, rec.A)
    return np.einsum("kji,kjl->il", rec.A, r_inv_a)


def batch_wls(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares estimate of pi and its covariance F^-1 (pseudo-inverse if F is
    singular: unobservable directions are then left at zero, see ``unobservable_directions``)."""
    fisher = fisher_information(rec)
    r_inv_y = np.linalg.solve(rec.R, (rec.z - rec.b)[..., None])[..., 0]
    g = np.einsum("kji,kj->i", rec.A, r_inv_y)
    cov = np.linalg.pinv(fisher, rcond=1e-12, hermitian=True)
    return cov @ g, cov


def derived_quantities(pi: np.ndarray) -> np.ndarray:
    """g(pi) = [mass, centre of mass (3), sorted principal moments about the centre of mass (3)]."""
    mass, com, inertia = mass_com_inertia_from_params(pi)
    return np.concatenate(([mass], com, principal_moments(inertia)))


def derived_covariance(pi: np.ndarray, cov: np.ndarray, step: float = 1e-7) -> np.ndarray:
    """G cov G^T for ``derived_quantities`` at pi (central differences, relative step)."""
    pi = np.asarray(pi, dtype=float)
    g0 = derived_quantities(pi)
    jac = np.zeros((g0.size, pi.size))
    for i in range(pi.size):
        h = step * max(abs(pi[i]), 1e-3)
        d = np.zeros_like(pi)
        d[i] = h
        jac[:, i] = (derived_quantities(pi + d) - derived_quantities(pi - d)) / (2 * h)
    return jac @ cov @ jac.T


def crlb(rec: Recording, pi_true: np.ndarray, prior_cov: np.ndarray | None = None) -> dict:
    """Cramer-Rao bound at the true parameters: standard deviations of pi and of the derived
    quantities (mass, CoM, principal moments). With ``prior_cov`` the Bayesian bound."""
    info = fisher_information(rec)
    if prior_cov is not None:
        info = info + np.linalg.inv(prior_cov)
    cov = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
    unobservable = unobservable_directions(info)
    derived = derived_covariance(pi_true, cov)
    std_params = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std_derived = np.sqrt(np.maximum(np.diag(derived), 0.0))
    if unobservable:
        # Unlearnable directions have no finite bound; mark what they touch.
        null = np.linalg.eigh(info)[1][:, : len(unobservable)]
        touched = np.abs(null).max(axis=1) > 1e-6
        std_params[touched] = np.inf
        jac_touch = np.abs(derived_covariance(pi_true, null @ null.T)).diagonal() > 1e-12
        std_derived[jac_touch] = np.inf
    return {
        "cov": cov,
        "std_params": std_params,
        "std_mass": float(std_derived[0]),
        "std_com": std_derived[1:4],
        "std_principal": std_derived[4:7],
        "unobservable": unobservable,
    }


def unobservable_directions(fisher: np.ndarray, rel_tol: float = 1e-9) -> list[np.ndarray]:
    """Unit directions in pi space with (relatively) zero Fisher information."""
    lam, vec = np.linalg.eigh(0.5 * (fisher + fisher.T))
    cutoff = rel_tol * max(float(lam.max()), 1e-300)
    return [vec[:, i] for i in range(lam.size) if lam[i] <= cutoff]


def unrevealed_directions(
    fisher: np.ndarray, prior_cov: np.ndarray, ratio: float = 0.01
) -> list[np.ndarray]:
    """Linear functionals u of pi (u^T pi) about which the data adds less than ``ratio`` of the
    prior's information (generalised eigenproblem F v = lam P0^-1 v, lam < ratio; u = P0^-1 v),
    normalised so that the prior variance u^T P0 u = 1. A trajectory that does not excite them
    cannot reveal them: an honest filter's variance u^T P u stays near 1."""
    prior_info = np.linalg.inv(prior_cov)
    chol = np.linalg.cholesky(0.5 * (prior_info + prior_info.T))
    inv_chol = np.linalg.inv(chol)
    lam, w = np.linalg.eigh(inv_chol @ fisher @ inv_chol.T)
    del inv_chol
    return [chol @ w[:, i] for i in range(lam.size) if lam[i] < ratio]


def convergence_time(times: np.ndarray, rel_err: np.ndarray, tol: float) -> float | None:
    """First time after which ``rel_err`` stays within ``tol`` (None if it never does)."""
    outside = np.nonzero(np.asarray(rel_err) > tol)[0]
    if outside.size == 0:
        return float(times[0])
    if outside[-1] == len(times) - 1:
        return None
    return float(times[outside[-1] + 1])
