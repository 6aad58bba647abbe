"""Bias compensation of the errors in variables: the reported estimate without the regressor's
noise bias (``CargoEstimator(bias_compensation=True)``).

The problem. Update k measures z = Y pi + b + v with a regressor Y and offset b that carry the
sensors' noise: in this robot's modes u (``NoiseModel.momentum_jacobians``: unit variance per
update at level var, lag-0 covariance Gm per channel), Y_meas = Y + sum_a dY_a u_a and
b_meas = b + sum_a dL_a u_a, so the residual is r = z - Y_meas pi - b_meas = -sum_a E_a u_a,
E_a = dL_a + dY_a pi (``motion.balance_noise_map``; with the team's mismatch conditioning the
conditioned (N - K D) map). The score of update k at x, g_k(x) = Y_meas^T R^-1 (z - Y_meas x -
b_meas), then has the expectation F_k (pi - x) + s_k(x) with the errors-in-variables term

    s_k(x) = -sum_(channels) sum_(a, b) Gm_ab dY_a^T R^-1 E_b(x)          (10,),
    ds_k / dx = -D_k,   D_k = sum_(channels) sum_(a, b) Gm_ab dY_a^T R^-1 dY_b   (10, 10),

(F_k = Y^T R^-1 Y). The filter solves sum_k g_k(x) = 0 (with its prior), so its estimate is off
by P sum_k s_k: relative size ~ var(dY) / var(Y), which the covariance R (which holds E E^T)
does not cover. Only the lag-0 covariance enters: the modes of two different updates are
correlated, but each score holds one update's regressor and residual.

The compensation (corrected least squares, deferred). The compensated estimate solves
P^-1 (x_c - x) = -sum_k s_k(x_c): the expected score is taken out of the data's. Each s_k is
evaluated where its maps were built (x0_k, the estimate before update k) and carried to x by
its slope, s_k(x) = s_k(x0_k) - D_k (x - x0_k) (exact for "own" fusion: E is affine in pi), and
the sum is evaluated at the filter's latest x:

    x_c = x + d,   d = -P (a - B x),   a = sum_k s_k(x0_k) + D_k x0_k,   B = sum_k D_k.

The filter's own path (x, P, its noise maps and gate) is untouched; only the report moves.
With a random walk Q, the older terms are discounted as the deferred recursion
d_k = P_k (P_(k-1) + Q)^-1 d_(k-1) - P_k s_k does: a, B <- (P_(k-1) + Q)^-1 P_(k-1) (a, B).
Evaluating at x instead of solving (P^-1 - B) x_c = P^-1 x - a leaves an error of order P B d
(P B: the regressor noise's share of the information, a few per cent): the exact form is
near-singular early, while P^-1 is still small along the directions the noise moves. P stays
the filter's: the compensated estimate's spread, (F - B)^-1 F (F - B)^-1, is larger by that
order.
"""

from __future__ import annotations

import numpy as np

from .motion import HELD_EXTENDED, POINT_EXTENDED
from .over_time import MODES_PER_CHANNEL


def score_bias(balance_map, d_y, groups, cov) -> tuple[np.ndarray, np.ndarray]:
    """(s (10,), D (10, 10)) of one update (module docstring): ``balance_map`` E (6, n) and
    ``d_y`` dY (n, 6, 10) of this robot's modes at unit per-update variance, ``groups`` the
    modes' (columns, channels, modes per channel, lag-0 covariance Gm (m, m)) (``mode_groups``),
    ``cov`` R (6, 6) the update's measurement covariance."""
    r_inv = np.linalg.inv(cov)
    score, slope = np.zeros(10), np.zeros((10, 10))
    for cols, channels, m, gm in groups:
        if not channels:
            continue
        d_yg = d_y[cols].reshape(channels, m, 6, 10)
        e_g = balance_map[:, cols].T.reshape(channels, m, 6)
        weighted = np.einsum("caxp,ab,xy->cbyp", d_yg, gm, r_inv)
        score -= np.einsum("cbyp,cby->p", weighted, e_g)
        slope += np.einsum("cbyp,cbyq->pq", weighted, d_yg)
    return score, 0.5 * (slope + slope.T)


def mode_groups(noise) -> list[tuple[slice, int, int, np.ndarray]]:
    """This robot's modes of a ``NoiseModel`` (no over-time window), grouped as ``score_bias``
    takes them: gyro, accelerometer (3 channels of 4 modes each), encoders (nj channels of 8)
    and squared rates (white, one each), with each channel's lag-0 covariance in its modes
    Gm = F^+ G(0) F^+T (F the per-update factor of ``momentum_jacobians``: the lag-weighted one
    for the IMU, so Gm != I there; G(0)'s own for the encoders, Gm = I)."""
    held = noise._lag_cov[0][np.ix_(HELD_EXTENDED, HELD_EXTENDED)]
    accel_factor, accel = noise._held_factor, held
    if noise._accel_factor is not None:
        accel_factor, accel = noise._accel_factor, noise._accel_lag_cov[0]
    point = noise._lag_cov[0][np.ix_(POINT_EXTENDED, POINT_EXTENDED)]
    nj, n_rates = noise._n_joints, noise._n_rate_modes
    imu = 3 * MODES_PER_CHANNEL
    return [
        (slice(0, imu), 3, MODES_PER_CHANNEL, _in_modes(noise._held_factor, held)),
        (slice(imu, 2 * imu), 3, MODES_PER_CHANNEL, _in_modes(accel_factor, accel)),
        (slice(2 * imu, 2 * imu + 8 * nj), nj, 8, _in_modes(noise._point_factor, point)),
        (slice(2 * imu + 8 * nj, 2 * imu + 8 * nj + n_rates), n_rates, 1, np.ones((1, 1))),
    ]


def _in_modes(factor: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """F^+ G F^+T: a channel's covariance G in the modes of its factor F."""
    inverse = np.linalg.pinv(factor)
    return inverse @ cov @ inverse.T


def own_modes(noise, fusion, params, motion_jac, regressor, peers, slope=True, known=None):
    """This robot's modes as the residual sees them, (E (6, n), dY (n, 6, 10)) at unit
    per-update variance (``NoiseModel.motion_noise``'s maps at ``params``: E = N's own columns,
    conditioned on the team's mismatch, N - K D, under "team" fusion with peers; dY None
    without ``slope``; E ``known`` where the motion noise's call has made it); None where the
    motion noise has no modes (fusion "none", no Jacobians, a peer without motion)."""
    if fusion == "none" or motion_jac is None:
        return None
    if any(m.motion_links_jac is None for _, m in peers):
        return None
    own = noise.momentum_motion
    args = (own, params, motion_jac, regressor, peers)
    modes = known if known is not None else noise.own_modes(*args, fusion == "team" and bool(peers))
    if not slope:
        return modes, None
    scale = np.sqrt(noise._team(*args)[3][: own.var.size])
    return modes, motion_jac[1] * scale[:, None, None]


class DeferredCompensation:
    """The sums a (10,) and B (10, 10) of the deferred compensation (module docstring)."""

    def __init__(self) -> None:
        self.a = np.zeros(10)
        self.B = np.zeros((10, 10))

    def add_update(self, noise, update, cov_before, walk) -> None:
        """``add`` the terms of a used update (``score_bias`` of its ``update`` = (E, dY) modes
        (``own_modes``), R and the params they are built at)."""
        modes, cov, params = update
        self.add((*score_bias(*modes, mode_groups(noise), cov), params), cov_before, walk)

    def add(self, terms, cov_before, walk) -> None:
        """Take in one used update's ``terms`` (s (10,), D (10, 10), where evaluated (10,)),
        the older ones discounted by (P_(k-1) + Q)^-1 P_(k-1) (``cov_before`` P_(k-1), ``walk``
        Q; none where Q = 0)."""
        score, slope, at = terms
        if np.any(walk):
            discount = np.linalg.solve(cov_before + walk, cov_before)
            self.a, self.B = discount @ self.a, discount @ self.B
        self.a = self.a + score + slope @ at
        self.B = self.B + slope

    def offset(self, x: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """d = -P (a - B x) (10,): the compensated estimate is x + d."""
        return -cov @ (self.a - self.B @ x)

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(a, B), shared: ``add`` replaces them, never changes them in place."""
        return self.a, self.B

    def restore(self, state: tuple[np.ndarray, np.ndarray]) -> None:
        self.a, self.B = state
