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

The last n_lags updates' V_k wait in a ring buffer for the next, which takes them in with one
compiled call (``add_cross_terms``): carried = sum_l V_l Gm(k - l) over the lags, then
C = carried V_k^T and X + C + C^T. The ring holds a rollback's depth more (``CargoEstimator``'s
snapshots), so a rollback restores X and the count alone (``state``, ``restore``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .copies import deepcopy_state
from .motion import POINT_EXTENDED
from .over_time import IMU_MODES

MODES = 8  # the encoders' modes per joint (``motion.POINT_EXTENDED``)


def encoder_lag_covariances(noise) -> np.ndarray:
    """Gm(L) (n_lags + 1, 8, 8) of a ``NoiseModel``'s encoder modes (module docstring)."""
    inverse = np.linalg.pinv(noise._point_factor)
    point = noise._lag_cov[:, POINT_EXTENDED][:, :, POINT_EXTENDED]
    return np.einsum("ab,lbc,dc->lad", inverse, point, inverse)


@njit(cache=True)
def encoder_weights(regressor, cov, encoder_map):
    """V = Y^T R^-1 E (10, 8 nj): ``regressor`` Y (6, 10), ``cov`` R (6, 6), ``encoder_map``
    E (6, 8 nj) the encoders' columns of the update's own modes' map."""
    return np.linalg.solve(cov, regressor).T @ np.ascontiguousarray(encoder_map)


@njit(cache=True)
def add_cross_terms(X, ring, ring_index, count, index, v, lag_cov):
    """X + C + C^T (10, 10), C = carried V_k^T, carried = sum_l V_l Gm(k - l) over the ring's
    last n_lags entries l with 0 < k - l <= n_lags (module docstring), one product with the
    lags' Gm stacked by slot.

    ``ring`` (10 nj, 8 capacity) holds V_l of the entry in slot s in columns 8 s ... 8 s + 7,
    row p nj + c for parameter p and joint c, entry ``count`` - 1 the latest; ``ring_index``
    (capacity,) their update counts l; ``index`` k and ``v`` V_k (10 nj, 8) the new update's;
    ``lag_cov`` Gm(L) (n_lags + 1, 8, 8)."""
    n_lags, capacity = lag_cov.shape[0] - 1, ring_index.shape[0]
    lags = np.zeros((capacity * MODES, MODES))  # Gm(k - l) in the rows of entry l's slot
    for back in range(1, min(count, n_lags) + 1):
        slot = (count - back) % capacity
        lag = index - ring_index[slot]
        if 0 < lag <= n_lags:
            lags[slot * MODES : (slot + 1) * MODES] = lag_cov[lag]
    carried = ring @ lags
    cross = carried.reshape(10, -1) @ v.reshape(10, -1).T
    return X + (cross + cross.T)  # exactly symmetric


@njit(cache=True)
def take_in(X, ring, ring_index, ring_count, count, index, regressor, cov, balance_map, start,
            stop, lag_cov):  # fmt: skip
    """``EncoderCovariance.add`` in one compiled call: V_k = Y^T R^-1 E (``encoder_weights``,
    E = ``balance_map``'s columns start ... stop - 1) as (10 nj, 8) rows, X + C + C^T
    (``add_cross_terms``, returned), then V_k into the ring's slot ``count`` mod capacity, with
    its update count ``index`` and entry ``count`` (``ring_index``, ``ring_count``)."""
    weights = encoder_weights(regressor, cov, balance_map[:, start:stop])
    v = weights.reshape(ring.shape[0], MODES)
    X = add_cross_terms(X, ring, ring_index, count, index, v, lag_cov)
    slot = count % ring_index.shape[0]
    ring[:, slot * MODES : (slot + 1) * MODES] = v
    ring_index[slot], ring_count[slot] = index, count
    return X


@njit(cache=True)
def sandwich(cov, X):
    """P + P X P (10, 10), symmetrised, for the filter's P ``cov``."""
    out = cov + cov @ X @ cov
    return 0.5 * (out + out.T)


@njit(cache=True)
def sandwich_std(P, X, out):
    """Into ``out`` (n,): sqrt of the diagonal of P + P X P (n, n), the standard deviations of
    the encoders' sandwich (``sandwich``) without the full product:
    out_i = sqrt(P_ii + sum_j (sum_k P_ik X_kj) P_ji)."""
    n = P.shape[0]
    for i in range(n):
        total = 0.0
        for j in range(n):
            row = 0.0
            for k in range(n):
                row += P[i, k] * X[k, j]
            total += row * P[j, i]
        out[i] = np.sqrt(P[i, i] + total)


class EncoderCovariance:
    """The cross terms X (10, 10) of the encoders' noise over the used updates (module
    docstring), with the last updates' (index, V) in a ring to pair with the next.

    X is replaced, never changed in place, so ``state`` holds it without a copy. The ring keeps
    ``rollback`` entries beyond the n_lags a new update pairs with: after ``state`` at count c,
    up to ``rollback`` more updates overwrite none of the entries c - n_lags ... c - 1, so
    ``restore`` needs only X and c."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(
        self, lag_cov: np.ndarray, columns: slice, n_joints: int, rollback: int = 0
    ) -> None:
        self.lag_cov = np.ascontiguousarray(lag_cov, dtype=float)  # Gm(L) (n_lags + 1, 8, 8)
        self.columns = columns  # the encoders' modes among the map's columns (8 per joint)
        self.n_joints = int(n_joints)
        self.n_lags = self.lag_cov.shape[0] - 1
        capacity = max(self.n_lags + int(rollback), 1)
        self.X = np.zeros((10, 10))
        self.ring = np.zeros((10 * self.n_joints, capacity * MODES))
        self.ring_index = np.zeros(capacity, dtype=np.int64)  # update counts of the entries
        self.ring_count = np.full(capacity, -1, dtype=np.int64)  # which entry each slot holds
        self.count = 0  # entries taken in so far

    @classmethod
    def of(cls, noise, rollback: int = 0) -> EncoderCovariance:
        """For a ``NoiseModel``'s modes (``momentum_jacobians``: the encoders after the IMU's),
        restorable over ``rollback`` updates."""
        nj = noise._n_joints
        columns = slice(IMU_MODES, IMU_MODES + MODES * nj)
        return cls(encoder_lag_covariances(noise), columns, nj, rollback)

    def add(self, index: int, regressor, cov, balance_map) -> None:
        """Take in a used update: its count ``index``, Y (6, 10), R (6, 6) and own modes' map
        E (6, n) (``own_modes``): V = Y^T R^-1 E's encoder columns (``take_in``)."""
        self.X = take_in(
            self.X, self.ring, self.ring_index, self.ring_count, self.count, int(index),
            regressor, cov, balance_map, self.columns.start, self.columns.stop, self.lag_cov,
        )  # fmt: skip
        self.count += 1

    def covariance(self, cov: np.ndarray) -> np.ndarray:
        """P + P X P (10, 10), symmetric, for the filter's P ``cov``."""
        return sandwich(np.ascontiguousarray(cov, dtype=float), self.X)

    def std(self, cov: np.ndarray, out: np.ndarray) -> None:
        """sqrt(diag(P + P X P)) (10,) into ``out`` (``sandwich_std``), for the filter's P."""
        sandwich_std(cov, self.X, out)

    def state(self) -> tuple[np.ndarray, int]:
        """(X, count): what ``restore`` needs, X shared (never changed in place)."""
        return self.X, self.count

    def restore(self, state: tuple[np.ndarray, int]) -> None:
        """Back to a ``state``; RuntimeError where the ring has overwritten an entry it pairs
        with (a rollback deeper than ``rollback``)."""
        X, count = state
        kept = np.arange(max(count - self.n_lags, 0), count)
        if np.any(self.ring_count[kept % self.ring_index.size] != kept):
            raise RuntimeError("rollback deeper than the encoders' covariance can restore")
        self.X, self.count = X, count
