"""The reported covariance with the encoders' noise correlated over updates
(``CargoEstimator(encoders_over_time=True)``, off by default).

The encoders' modes enter each update at their per-update covariance C(0) (``noise_model``:
the lag-weighted W, exact for a scalar regressor only, is far below it and too confident). But
the slow filter's memory (3-4 s with its tail) spans many updates, so the encoders' noise in the
balances of updates k and l is correlated:

    Cov(e_k, e_l) = E_k Gm(l - k) E_l^T,   Gm(L) = F^+ G(L) F^+T,

E_k (6, 8 nj) the encoders' columns of update k's conditioned noise map at unit per-update
variance (``bias_compensation.own_modes``), G(L) (8, 8) the point channel's kernels' lag
covariance between updates L apart (``motion.kernel_lag_covariances``; zero beyond the chain's
n_lags) and F its per-update factor (F F^T = G(0)). The filter treats updates as independent
(Q = 0): x - pi = P (P0^-1 (x0 - pi) + sum_k Y_k^T R_k^-1 e_k), so the estimate's covariance
under the model's own noise is

    P + P X P,   X = sum_(k != l) V_k Gm(l - k) V_l^T,   V_k = Y_k^T R_k^-1 E_k   (10, 8 nj),

the sandwich of the information the filter counts (P^-1 = P0^-1 + sum_k Y_k^T R_k^-1 Y_k, which
holds each update's own R_k) and the cross terms it leaves out. Nothing is tuned: X is the sum of
the same modes' lag covariances the IMU's channels are weighed with (``over_time``), over the
pairs of used updates within n_lags of each other, per encoder channel (the joints' noises are
independent). The estimate itself is unchanged; only ``params_cov`` (and the spread of
``physical_estimate``) report it. X runs over the updates' own regressors, so it is exact for
any motion, where the lag-weighted W with one autocorrelation rho is not (the floors' case,
``scripts/floors_consistency.py``). With a random walk (Q != 0) the older terms would need the
filter's discount; the option requires Q = 0.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .motion import POINT_EXTENDED
from .over_time import IMU_MODES


def encoder_lag_covariances(noise) -> np.ndarray:
    """Gm(L) (n_lags + 1, 8, 8) of a ``NoiseModel``'s encoder modes (module docstring)."""
    inverse = np.linalg.pinv(noise._point_factor)
    point = noise._lag_cov[:, POINT_EXTENDED][:, :, POINT_EXTENDED]
    return np.einsum("ab,lbc,dc->lad", inverse, point, inverse)


class EncoderCovariance:
    """The cross terms X (10, 10) of the encoders' noise over the used updates (module
    docstring), with the last n_lags updates' (index, V) to pair with the next."""

    def __init__(self, lag_cov: np.ndarray, columns: slice, n_joints: int) -> None:
        self.lag_cov = lag_cov  # Gm(L) (n_lags + 1, 8, 8)
        self.columns = columns  # the encoders' modes among the map's columns (8 per joint)
        self.n_joints = int(n_joints)
        self.X = np.zeros((10, 10))
        self.recent: deque[tuple[int, np.ndarray]] = deque(maxlen=self.lag_cov.shape[0] - 1)

    @classmethod
    def of(cls, noise) -> EncoderCovariance:
        """For a ``NoiseModel``'s modes (``momentum_jacobians``: the encoders after the IMU's)."""
        nj = noise._n_joints
        return cls(encoder_lag_covariances(noise), slice(IMU_MODES, IMU_MODES + 8 * nj), nj)

    def add(self, index: int, regressor, cov, balance_map) -> None:
        """Take in a used update: its count ``index``, Y (6, 10), R (6, 6) and own modes' map
        E (6, n) (``own_modes``)."""
        v = np.linalg.solve(cov, regressor).T @ balance_map[:, self.columns]
        v = v.reshape(10, self.n_joints, 8)
        lags = np.array([index - earlier for earlier, _ in self.recent], dtype=int)
        near = (lags > 0) & (lags < self.lag_cov.shape[0])
        if near.any():
            earlier = np.stack([v_e for (_, v_e), n in zip(self.recent, near, strict=True) if n])
            # sum_l V_l Gm(k - l), then its product with V_k: sum_(l, c, a, b) of
            # V_l[p, c, a] Gm[a, b] V_k[q, c, b], the pairs' sum without a five-index loop.
            carried = np.matmul(earlier, self.lag_cov[lags[near]][:, None]).sum(axis=0)
            cross = carried.reshape(10, -1) @ v.reshape(10, -1).T
            self.X += cross + cross.T
        self.recent.append((index, v))

    def covariance(self, cov: np.ndarray) -> np.ndarray:
        """P + P X P (10, 10), symmetric, for the filter's P ``cov``."""
        out = cov + cov @ self.X @ cov
        return 0.5 * (out + out.T)

    def state(self):
        return self.X.copy(), list(self.recent)

    def restore(self, state) -> None:
        self.X = state[0].copy()
        self.recent.clear()
        self.recent.extend(state[1])
