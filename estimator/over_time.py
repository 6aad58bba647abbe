"""Updates conditioned on the previous ones: the IMU's noise weighed over time.

The slow filter's memory (about 1 s, 3-4 s with its tail) spans many updates (6.25 Hz), so the
IMU's noise in the balances of successive updates is correlated. ``noise_model`` carries it
per update; a filter that treats updates as independent must then enter it at a lag-weighted
covariance W (``motion.lag_weighted_covariance``), exact for a scalar regressor only. Here the
correlation is used instead: the balance errors e_k = z_k - Y_k pi - b_k of the last L used
updates and of update k are jointly Gaussian with

    Sigma_kl = J_k Gm(l - k) J_l^T   (k != l),        Sigma_kk = R_k,

J_k (6, 4 c) the conditioned noise map of the team's c IMU channels (``NoiseModel.
over_time_noise``: its modes of unit per-update variance, 4 per channel), Gm(L) (4, 4) the
covariance of one channel's modes L updates apart (``mode_lag_covariances``, the same for every
channel and robot: the robots' sensors are independent and their chains the same) and R_k the
update's whole covariance (the IMU's part J_k J_k^T plus what is white across updates: floors,
actuation, peers' channel noise, the encoders (errors in variables, see ``noise_model``), the
squared rates and the mismatch's model error). The Gaussian conditional of e_k on the window's
e_p (stacked, 6 L),

    A = Sigma_kp Sigma_pp^-1,    e_k - A e_p ~ N(0, R' = R_k - A Sigma_kp^T),

is independent of the window (the innovations form), so the update

    z' = z_k - A z_p,   Y' = Y_k - A Y_p,   b' = b_k - A b_p,   R'

enters a filter that treats updates as independent with its exact covariance (the balance is
linear in pi: the UKF stays exact). Exact for a Gaussian given the window: with the whole run
as window it is generalised least squares over the run; the window conditions on every update it
holds, also those beyond the chain's memory (correlated with this one through the updates
between; ``DEFAULT_WINDOW``). Skipped, gated and rolled-back updates are not in it (conditioning
on the used subset is as exact). Cost per update: one (6 L, 6 L) Cholesky solve.

Off by default (``CargoEstimator(over_time_window=0)``): measured (docs/estimation_limits.md), it
gives the whole run's bound, above the lag-weighted one, and with every noise source its NEES
leaves the band. The cause is a bias, not this covariance: the regressor holds the accelerometer's
and the encoders' noise (errors in variables, biased as the noise's square); conditioning whitens
the regressor's noise with the balance's while the slow excitation is scaled down with the noise's
low frequencies, so the bias grows several times against the std. A covariance cannot cover it;
a bias-compensated update would.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np
from numba import njit

from .motion import gain_of

# Updates of the window: for the default chain the modes' lag covariance Gm(L) has fallen to
# 1.3e-2 of Gm(0) at 25 updates (4 s at 6.25 Hz) and 2e-3 at 30 (``mode_lag_covariances``);
# measured, 8 and 24 give the whole run's generalised least squares to 2 digits of the bound.
DEFAULT_WINDOW = 24
# Modes per IMU channel (``motion.HELD_EXTENDED``: value->value, value->derivative, their twins).
MODES_PER_CHANNEL = 4
# A robot's IMU modes (gyro and accelerometer, 3 axes each), the first of its modes
# (``NoiseModel.momentum_jacobians``) and of its message's (``NoiseModel.message_modes``).
IMU_MODES = 6 * MODES_PER_CHANNEL


def mode_lag_covariances(held_lag_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The modes of a held channel at its per-update covariance and their covariance over time:
    (F (4, 4), Gm (n_lags + 1, 4, 4)) with F F^T = G(0) = U S U^T, F = U S^1/2, and
    Gm(L) = F^+ G(L) F^+T, F^+ = S^-1/2 U^T on G(0)'s range; G (n_lags + 1, 4, 4) the kernels'
    lag covariances (``motion.kernel_lag_covariances`` over ``HELD_EXTENDED``): the modes
    u = F^+ eps of the kernels' outputs eps at one update and L updates later have the
    covariance Gm(L) per unit per-sample variance, Gm(0) = I on the range. Read-only."""
    s, u = np.linalg.eigh(held_lag_cov[0])
    keep = s > 0
    factor = u * np.sqrt(np.clip(s, 0.0, None))
    inv = np.zeros_like(held_lag_cov[0])
    inv[keep] = (u[:, keep] / np.sqrt(s[keep])).T
    out = inv @ held_lag_cov @ inv.T
    for a in (factor, out):
        a.setflags(write=False)
    return factor, out


@njit(cache=True)
def conditioning_gain(n_map, d_map, level, mismatch_model_var):
    """K = S_nd S_dd^+ (6, 3 P) of ``motion.conditioned_maps``: the remaining map is N - K D.
    S_dd's eigenvalues are at least ``mismatch_model_var``, so K comes from ``motion.gain_of``
    (S_dd^-1 by Cholesky where that floor keeps pinv's cut away, as ``conditioned_maps``)."""
    d_map_t = np.ascontiguousarray(d_map.T)
    s_nd = (n_map * level) @ d_map_t
    s_dd = (d_map * level) @ d_map_t + mismatch_model_var * np.eye(d_map.shape[0])
    return gain_of(s_nd, s_dd, mismatch_model_var)


@njit(cache=True)
def cross_covariance_channels(earlier, later, mode_covs):
    """``cross_covariance`` with one Gm(l - k) per robot channel: ``mode_covs`` (6, 4, 4),
    channel c's ``mode_covs[c % 6]`` (the fused accelerometer's, ``noise_model``)."""
    out = np.zeros((6, 6))
    for c in range(earlier.shape[1]):
        gm = np.ascontiguousarray(mode_covs[c % 6])
        out += np.ascontiguousarray(earlier[:, c]) @ gm @ np.ascontiguousarray(later[:, c]).T
    return out


@njit(cache=True)
def cross_covariance(earlier, later, mode_cov):
    """Sigma_kl = sum_c J_k,c Gm J_l,c^T (6, 6): ``earlier`` J_k and ``later`` J_l (6, c, 4),
    ``mode_cov`` Gm(l - k) (4, 4)."""
    out = np.zeros((6, 6))
    for c in range(earlier.shape[1]):
        out += np.ascontiguousarray(earlier[:, c]) @ mode_cov @ np.ascontiguousarray(later[:, c]).T
    return out


class WindowEntry(NamedTuple):
    """One used update: its update count, stamp, measurement (z (6,), Y (6, 10), b (6,)),
    whole covariance R (6, 6), IMU map J (6, c, 4) and its covariances with the window's
    earlier entries, {stamp: Sigma_earlier,this (6, 6)}."""

    index: int
    stamp: int
    z: np.ndarray
    regressor: np.ndarray
    offset: np.ndarray
    cov: np.ndarray
    imu_map: np.ndarray
    cross: dict


class UpdateWindow:
    """The last ``length`` used updates and the conditioning of a new one on them (module
    docstring). ``mode_lag_cov`` Gm (n_lags + 1, 4, 4), or one per robot channel
    (n_lags + 1, 6, 4, 4) (``cross_covariance_channels``); ``update_every`` control steps per
    update (stamps are control steps)."""

    def __init__(self, mode_lag_cov: np.ndarray, length: int, update_every: int) -> None:
        if length < 1:
            raise ValueError(f"the window must hold at least 1 update, got {length}")
        self.mode_lag_cov = mode_lag_cov
        self._cross = cross_covariance_channels if mode_lag_cov.ndim == 4 else cross_covariance
        self.update_every = int(update_every)
        self.entries: deque[WindowEntry] = deque(maxlen=int(length))
        # Sigma_pp (6 m, 6 m) of the entries, kept as they come and go; the stacked z, Y, b.
        self._sigma = np.zeros((0, 0))
        self._stacked = (np.zeros(0), np.zeros((0, 10)), np.zeros(0))

    def clear(self) -> None:
        self.entries.clear()
        self._keep(0, 0)

    def drop_from(self, stamp: int) -> None:
        """Forget the entries of ``stamp`` and later (rolled back)."""
        while self.entries and self.entries[-1].stamp >= stamp:
            self.entries.pop()
        self._keep(0, len(self.entries))

    def _keep(self, first: int, stop: int) -> None:
        """Keep the rows of entries first..stop-1 of Sigma_pp and the stacked measurements."""
        rows = slice(6 * first, 6 * stop)
        self._sigma = self._sigma[rows, rows]
        self._stacked = tuple(x[rows] for x in self._stacked)

    def condition(self, stamp, z, regressor, offset, cov, imu_map):
        """(z', Y', b', R') of update ``stamp`` conditioned on the window, and its entry (to
        ``add`` once the update is used). ``imu_map`` None (a peer without the IMU's modes):
        the update as it is, and the window restarts after it."""
        if imu_map is None:
            return (z, regressor, offset, cov), None
        index = stamp // self.update_every
        if any(e.imu_map.shape != imu_map.shape for e in self.entries):
            self.clear()  # another team: its channels are not these
        n_lags = self.mode_lag_cov.shape[0] - 1
        cross = {}
        for e in self.entries:
            lag = index - e.index
            if lag <= n_lags:
                cross[e.stamp] = self._cross(e.imu_map, imu_map, self.mode_lag_cov[lag])
            else:  # beyond the chain's memory: correlated only through the updates between
                cross[e.stamp] = np.zeros((6, 6))
        entry = WindowEntry(index, stamp, z, regressor, offset, cov, imu_map, cross)
        if not self.entries:
            return (z, regressor, offset, cov), entry
        # Sigma_kp's block i is Cov(e_k, e_i) = Sigma_ik^T.
        s_kp = np.hstack([cross[e.stamp].T for e in self.entries])
        chol = np.linalg.cholesky(self._sigma)
        gain = np.linalg.solve(chol.T, np.linalg.solve(chol, s_kp.T)).T
        z_p, y_p, b_p = self._stacked
        cond = cov - gain @ s_kp.T
        return (z - gain @ z_p, regressor - gain @ y_p, offset - gain @ b_p,
                0.5 * (cond + cond.T)), entry  # fmt: skip

    def add(self, entry: WindowEntry | None) -> None:
        """Keep a used update's entry (None: restart the window): Sigma_pp grows by its row and
        column (its covariances with the entries, held in the entry) and loses the oldest's."""
        if entry is None:
            self.clear()
            return
        col = np.vstack([entry.cross[e.stamp] for e in self.entries] or [np.zeros((0, 6))])
        self._sigma = np.block([[self._sigma, col], [col.T, entry.cov]])
        self._stacked = tuple(
            np.concatenate((x, y))
            for x, y in zip(self._stacked, (entry.z, entry.regressor, entry.offset), strict=True)
        )
        full = len(self.entries) == self.entries.maxlen
        self.entries.append(entry)
        if full:
            self._keep(1, len(self.entries) + 1)
