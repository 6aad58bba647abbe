"""The motion noise of the wrench balance, and what the team's IMUs know about it.

The balance of robot i (``rne``, grasp frame G_i, moments about the grasp point)

    thrust_i = links_i(xi_i) + Y_i(xi_i) pi - sum_j T_ij W_j,   W_j = thrust_j - links_j(xi_j)

is built from each robot's filtered motion xi = (a_B (3), wd_B (3), qdd (n_joints)): the base
origin's linear acceleration (accelerometer), the base's angular acceleration (differentiated
gyro) and the joint accelerations (doubly differentiated encoders), base frame. For fixed angular
rate, joint angles and joint rates the balance is affine in xi, so an error dxi_i of robot i's
filtered motion and dxi_j of each peer's move the model side A pi + b by

    n = E_i dxi_i + sum_j T_ij L_j dxi_j,       E_i = d(links_i + Y_i pi)/dxi_i,
                                                 L_j = d(links_j)/dxi_j  (in G_j, about G_j),

a 6-vector whose covariance E Sigma E^T has the structure of the motion's noise: one
accelerometer's error moves the force rows by M a and the moment rows by c x a (c the mass-weighted
lever of the moved bodies), fully correlated (``balance_noise``). A diagonal covariance that
ignores this correlation throws that information away.

Every robot and the cargo move as one rigid body (the grasps are rigid; the arms move the bases
relative to the cargo, which the encoders see). So the cargo's acceleration at robot j's grasp
point is measured twice: by robot j (its IMU carried through its arm) and by robot i (its IMU
carried through its arm, then across the cargo: a_Gj = a_Gi + (skew(wd) + skew(w)^2) r_ij). The
mismatch of the two, d_j = R_ij a_Gj - a_Gi - Omega_i r_ij, is zero up to the motion errors,

    d_j = R_ij G_j dxi_j - G_ij dxi_i,

and conditioning the Gaussian (n, d) on the observed d (``condition_on_mismatch``) gives the
balance noise that remains once every IMU of the team has been heard:

    E[n | d] = S_nd S_dd^-1 d,        Cov[n | d] = S_nn - S_nd S_dd^-1 S_nd^T,

S = the joint covariance of (n, d) from Sigma = blockdiag(Sigma_i, Sigma_j, ...). The measurement
then uses b - E[n | d] and the covariance Cov[n | d]: the common part of the accelerometer errors
(what all robots agree on) stays, the differences are removed; for the moment rows about the
assembly's centre of mass the common linear-acceleration error drops out altogether.

All quantities here are filtered ones (the same slow filter runs over every balance term, so
dxi is the filter's output noise); Sigma is the diagonal covariance of that filtered noise per
motion coordinate. Everything is linear; the Jacobians are exact: the balance's acceleration
part (``rne.balance_motion_jacobians``), or unit differences of any affine balance
(``motion_jacobians``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from numba import njit

from .copies import deepcopy_state
from .preprocess import StateVariableFilter


def motion_jacobians(
    balance: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], xi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of (links_G (6,), Y (6, 10)) with respect to the motion ``xi`` (n,).

    ``balance(xi)`` returns the links' momentum rate and the cargo's body regressor for motion xi
    with everything else held; it is affine in xi, so unit differences are exact. Returns
    (dlinks (6, n), dY (n, 6, 10))."""
    xi = np.asarray(xi, dtype=float)
    if xi.ndim != 1:
        raise ValueError(f"xi must be a vector, got shape {xi.shape}")
    links0, y0 = balance(xi)
    d_links = np.empty((6, xi.size))
    d_y = np.empty((xi.size, 6, 10))
    for k in range(xi.size):
        step = xi.copy()
        step[k] += 1.0
        links1, y1 = balance(step)
        d_links[:, k] = links1 - links0
        d_y[k] = y1 - y0
    return d_links, d_y


@njit(cache=True)
def balance_noise_map_kernel(d_links, d_y, params) -> np.ndarray:
    """E (6, n): column k is d links / dxi_k + (d Y / dxi_k) pi (``balance_noise_map``, compiled
    and unchecked, for compiled callers), each entry's sum over pi's 10 entries as one loop."""
    n_map = np.empty((6, d_y.shape[0]))
    for r in range(6):
        for k in range(d_y.shape[0]):
            moved = 0.0
            for p in range(10):
                moved += d_y[k, r, p] * params[p]
            n_map[r, k] = d_links[r, k] + moved
    return n_map


@njit(cache=True)
def grasp_acc_map_kernel(d_y: np.ndarray, point_g: np.ndarray) -> np.ndarray:
    """G (3, n): column k is the force rows' a column plus their h columns times the point
    (``grasp_acc_map``, compiled and unchecked, for compiled callers)."""
    n = d_y.shape[0]
    lever = grasp_acc_h_rows(d_y) @ point_g  # one product
    return np.ascontiguousarray(d_y[:, :3, 0].T) + np.ascontiguousarray(lever.reshape(n, 3).T)


@njit(cache=True)
def grasp_acc_h_rows(d_y: np.ndarray) -> np.ndarray:
    """The force rows' h columns of every d Y_k stacked (3 n, 3), row 3 k + i: d Y_k[i, 1:4]
    (``grasp_acc_map_kernel``'s lever is this times the point)."""
    return np.ascontiguousarray(d_y[:, :3, 1:4]).reshape(3 * d_y.shape[0], 3)


@njit(cache=True)
def pinv_symmetric(a: np.ndarray, rcond: float = 1e-15) -> np.ndarray:
    """Pseudo-inverse of a symmetric matrix from its eigen-decomposition a = U diag(s) U^T:
    U diag(1 / s) U^T over the eigenvalues with |s| > rcond max |s| (the others give 0), which
    is ``np.linalg.pinv(a, hermitian=True)``."""
    if a.shape[0] == 0:
        return a.copy()
    s, u = np.linalg.eigh(a)
    cutoff = rcond * np.max(np.abs(s))
    inv = np.zeros_like(s)
    for k in range(s.shape[0]):
        if abs(s[k]) > cutoff:
            inv[k] = 1.0 / s[k]
    return (u * inv) @ u.T


@njit(cache=True)
def gain_of(cross, sym, floor, rcond=1e-15):
    """K = C A^+ (m, n) for a symmetric A (n, n) = ``sym`` whose eigenvalues are known to be at
    least ``floor`` (A = B + floor I, B positive semi-definite) and C (m, n) = ``cross``.

    Where floor > 100 rcond tr(A) no eigenvalue falls under pinv's cut (rcond max |s| <=
    rcond tr(A), with room for rounding), so A^+ = A^-1 and each row k of K solves A k = c by
    Cholesky, A = L L^T: L y = c, then L^T k = y. Otherwise K = C ``pinv_symmetric``(A)."""
    n = sym.shape[0]
    if n == 0 or not floor > 100.0 * rcond * np.trace(sym):
        return cross @ pinv_symmetric(sym, rcond)
    lower = np.linalg.cholesky(sym)
    gain = np.empty(cross.shape)
    for r in range(cross.shape[0]):
        for i in range(n):  # forward: L y = c
            total = cross[r, i]
            for j in range(i):
                total -= lower[i, j] * gain[r, j]
            gain[r, i] = total / lower[i, i]
        for i in range(n - 1, -1, -1):  # backward: L^T k = y
            total = gain[r, i]
            for j in range(i + 1, n):
                total -= lower[j, i] * gain[r, j]
            gain[r, i] = total / lower[i, i]
    return gain


@njit(cache=True)
def noise_cov(n_map: np.ndarray, level: np.ndarray) -> np.ndarray:
    """N diag(level) N^T (6, 6), symmetrised: the unconditioned balance noise."""
    s_nn = (n_map * level) @ np.ascontiguousarray(n_map.T)
    return 0.5 * (s_nn + s_nn.T)


@njit(cache=True)
def conditioned_maps(n_map, d_map, level, mismatch, mismatch_model_var):
    """E[n | d] (6,), Cov[n | d] (6, 6) and the remaining map N - K D for n = N dxi,
    d = D dxi + e with Cov dxi = diag(level) and Cov e = mismatch_model_var I
    (``condition_on_mismatch`` on stacked maps):

    K = S_nd S_dd^+,  S_nd = N diag(level) D^T,  S_dd = D diag(level) D^T + var I,
    E[n | d] = K d,   Cov[n | d] = (N - K D) diag(level) (N - K D)^T + var K K^T."""
    d_map_t = d_map.T
    s_nd = (n_map * level) @ d_map_t
    s_dd = (d_map * level) @ d_map_t + mismatch_model_var * np.eye(d_map.shape[0])
    # Pseudo-inverse where noiseless motion coordinates (perfect sensors) and no mismatch
    # model make S_dd singular; its inverse, by Cholesky, where var bounds it away (``gain_of``).
    gain = gain_of(s_nd, s_dd, mismatch_model_var)
    remaining = n_map - gain @ d_map
    cov = (remaining * level) @ remaining.T
    cov += (mismatch_model_var * gain) @ gain.T
    return gain @ mismatch, 0.5 * (cov + cov.T), remaining


@njit(cache=True)
def scaled_own_modes(n_map, level, n_own):
    """The first ``n_own`` columns of a noise map at unit variance, N[:, :n_own]
    diag(level[:n_own])^1/2 (6, n_own)."""
    return np.ascontiguousarray(n_map[:, :n_own]) * np.sqrt(level[:n_own])


@njit(cache=True)
def conditioned_own_modes(n_map, d_map, level, condition, mismatch_model_var, n_own):
    """This robot's modes as the residual sees them (``scaled_own_modes``): of the remaining
    map N - K D (``conditioned_maps``) when ``condition``, else of N."""
    if condition:
        no_mismatch = np.zeros(d_map.shape[0])
        remaining = conditioned_maps(n_map, d_map, level, no_mismatch, mismatch_model_var)[2]
        return scaled_own_modes(remaining, level, n_own)
    return scaled_own_modes(n_map, level, n_own)


@njit(cache=True)
def posterior_spread(d_y, level, params_cov):
    """sum_k level_k dY_k P dY_k^T (6, 6), exactly symmetric: the regressor noise's spread over
    the posterior P (10, 10), for the (n, 6, 10) d Y and the first n entries of ``level``;
    dY_k P for every k as one product over the stacked (6 n, 10) rows, then the lower
    triangle's sums over k and P's index as one loop, mirrored."""
    n = d_y.shape[0]
    moved = (np.ascontiguousarray(d_y).reshape(6 * n, 10) @ params_cov).reshape(n, 6, 10)
    spread = np.empty((6, 6))
    for i in range(6):
        for j in range(i + 1):
            total = 0.0
            for k in range(n):
                term = 0.0
                for p in range(10):
                    term += moved[k, i, p] * d_y[k, j, p]
                total += level[k] * term
            spread[i, j] = spread[j, i] = total
    return spread


@njit(cache=True)
def conditioned_noise(n_map, d_map, mismatch, level, condition, mismatch_model_var, d_y,
                       params_cov, with_spread):  # fmt: skip
    """Mean (6,) and covariance (6, 6) of the motion noise from the team's maps
    (``team_noise.team_maps``): conditioned on the mismatch (``conditioned_maps``) or not
    (``noise_cov``), plus the posterior's spread (``posterior_spread``) when
    ``with_spread``; and this robot's modes as the residual sees them (6, n)
    (``conditioned_own_modes``, n = d_y's count), from the same remaining map."""
    n_own = d_y.shape[0]
    if condition:
        mean, cov, remaining = conditioned_maps(n_map, d_map, level, mismatch, mismatch_model_var)
        modes = scaled_own_modes(remaining, level, n_own)
    else:
        mean, cov = np.zeros(6), noise_cov(n_map, level)
        modes = scaled_own_modes(n_map, level, n_own)
    if with_spread:
        cov = cov + posterior_spread(d_y, level, params_cov)
    return mean, cov, modes


def balance_noise_map(d_links: np.ndarray, d_y: np.ndarray, params: np.ndarray) -> np.ndarray:
    """E = d(links + Y pi)/dxi (6, n) at parameters pi (10,)."""
    return balance_noise_map_kernel(_float(d_links), _float(d_y), _float(params))


def grasp_acc_map(d_y: np.ndarray, point_g: np.ndarray | None = None) -> np.ndarray:
    """G = d a_P / dxi (3, n): the acceleration of the cargo point P (``point_g``, G axes and
    origin; None: the grasp point) from the regressor's force rows, whose column m is a_G and
    columns h are skew(wd) + skew(w)^2 (so a_P = a_G + (skew(wd) + skew(w)^2) p)."""
    point = np.zeros(3) if point_g is None else _float(point_g)
    return grasp_acc_map_kernel(_float(d_y), point)


def _float(x) -> np.ndarray:
    """``x`` as a contiguous float64 array (what the compiled kernels take)."""
    return np.ascontiguousarray(x, dtype=float)


def condition_on_mismatch(
    noise_maps: list[np.ndarray],
    mismatch_maps: list[np.ndarray],
    variances: list[np.ndarray],
    mismatch: np.ndarray | None,
    band_factors: list[np.ndarray] | None = None,
    mismatch_model_var: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the balance noise n = sum_r N_r dxi_r given the observed
    mismatches d = sum_r D_r dxi_r (robots r independent, Cov dxi_r = diag(variances[r])).

    ``noise_maps[r]`` (6, n_r); ``mismatch_maps[r]`` (m, n_r) with m = 3 per peer (zero rows
    for a robot that does not enter a mismatch); ``mismatch`` (m,) or None (no peer motion
    heard: the unconditioned (0, N Sigma N^T)).

    ``band_factors`` (per coordinate, default 1; ``band_factors``) weight each source for its
    colour: the conditioning is done on the levels var * factor each source has in the band
    where the excitation lives (a differentiated encoder's per-sample noise is mostly above it
    and must not hide the accelerometers' difference in d), and the remaining noise
    n - K d = sum_r (N_r - K D_r) dxi_r is returned at those levels.

    ``mismatch_model_var`` ((m/s^2)^2 per axis, per update, white-equivalent): what the model
    leaves in d with perfect sensors (the pre-filter's distortion of the products), independent
    of the sensors: S_dd + mismatch_model_var I, and K's residual adds K (var I) K^T. That error
    varies as slowly as the filtered balance, so it enters at its rms^2 times the updates per
    decorrelation time, like the floors (``noise_model``): read as white per update at its rms,
    the gain carried it into the moment rows unmodelled (2 robots, tumble, accelerometer noise
    alone: K d_model 3-8e-5 N m rms against the balance's own 0.2-0.7e-5, NEES 23)."""
    n_map = np.hstack(noise_maps)
    var = np.concatenate([np.asarray(v, dtype=float) for v in variances])
    if n_map.shape != (6, var.size):
        raise ValueError(f"noise maps give shape {n_map.shape}, variances {var.size} coordinates")
    weight = np.ones(var.size) if band_factors is None else np.concatenate(band_factors)
    if weight.shape != var.shape:
        raise ValueError(f"band_factors give {weight.size} coordinates, variances {var.size}")
    level = _float(var * weight)
    if mismatch is None or not mismatch_maps:
        return np.zeros(6), noise_cov(_float(n_map), level)
    d_map = np.hstack(mismatch_maps)
    if d_map.shape != (np.size(mismatch), var.size):
        raise ValueError(f"mismatch maps give shape {d_map.shape}, mismatch {np.shape(mismatch)}")
    return conditioned_maps(
        _float(n_map), _float(d_map), level, _float(mismatch), float(mismatch_model_var)
    )[:2]


@functools.lru_cache(maxsize=16)
def filtered_motion_gains(
    dt_s: float,
    kinematics_cutoff_hz: float,
    cutoff_hz: float,
    regressor_every: int,
    n_delays: float = 8.0,
) -> np.ndarray:
    """Standard deviation of the balance's filtered motion per unit white noise per sample (3,):
    of the pre-filter's value (accelerometer -> a_B), first derivative (gyro -> wd_B) and second
    derivative (encoders -> qdd), each sampled every ``regressor_every`` steps and passed through
    the slow filter's value, the chain the estimator runs (``preprocess``, ``cargo_estimator``).

    Exact for the linear chain: the output at one slow-filter sample is sum_k g_k u_k, so its
    variance is sum_k g_k^2; the g_k are the responses to one impulse per input step (one channel
    each), over ``n_delays`` delays of the two filters. Cached: every robot shares its chain."""
    if regressor_every < 1:
        raise ValueError(f"regressor_every must be >= 1, got {regressor_every}")

    pre = StateVariableFilter(1, dt_s, kinematics_cutoff_hz)
    slow = StateVariableFilter(1, dt_s * regressor_every, cutoff_hz)
    span = int(np.ceil(n_delays * (pre.delay_s + slow.delay_s) / dt_s))
    span += regressor_every - span % regressor_every  # output at a slow-filter sample
    # The accelerometer and the gyro are period means (held channels, ``preprocess``); the
    # encoders point samples.
    pre = StateVariableFilter(3 * span, dt_s, kinematics_cutoff_hz, held=slice(0, 2 * span))
    slow = StateVariableFilter(3 * span, dt_s * regressor_every, cutoff_hz)
    # A first sample sets a filter's state (no start-up transient): start both at rest at zero.
    pre.step(np.zeros(3 * span))
    slow.step(np.zeros(3 * span))
    # Channel (c, k): source c (0 value, 1 rate, 2 angle), impulse at input step k.
    impulse = np.zeros((span + 1, 3 * span))
    for c in range(3):
        impulse[np.arange(span), c * span + np.arange(span)] = 1.0
    out = np.zeros(3 * span)
    for k in range(span + 1):
        y, yd, ydd = pre.step(impulse[k])
        if k % regressor_every == 0:
            src = np.concatenate((y[:span], yd[span : 2 * span], ydd[2 * span :]))
            out, _, _ = slow.step(src)
    return np.sqrt((out.reshape(3, span) ** 2).sum(axis=1))


def band_factors(
    gains: np.ndarray,
    dt_s: float,
    kinematics_cutoff_hz: float,
    cutoff_hz: float,
    update_every: int,
) -> np.ndarray:
    """Per-update weight of each filtered motion source (value, rate, second derivative) (3,):
    the measurement covariance treats the updates, every ``update_every`` steps, as independent,
    so each source enters as white noise at the highest level its filtered spectrum reaches
    below the slow filter's cutoff, where the excitation lives:

        factor_c = max_{f <= cutoff} S_c(f) / (2 dt_update var_c),
        S_c(f) = 2 dt (2 pi f)^(2c) |H_pre(f)|^2 |H_slow(f)|^2   (unit white noise per sample),

    var_c = ``gains[c]``^2 (``filtered_motion_gains``). For white noise (c = 0) the maximum is at
    f = 0 and the factor is the filter's decorrelation factor; a differentiated source (gyro to
    angular acceleration, c = 1; encoders to joint acceleration, c = 2) has most of its power
    above the cutoff, where the balance's slow filter removes it, and a factor near 1. Replacing
    a spectrum by its maximum over the signal band can only lose information: the bound stays
    conservative."""
    gains = np.asarray(gains, dtype=float)
    freq = np.linspace(0.0, cutoff_hz, 2001)[1:]
    w = 2 * np.pi * freq

    def power(fc: float) -> np.ndarray:  # |(wc / (s + wc))^3|^2 with the -3 dB point at fc
        wc = 2 * np.pi * fc / np.sqrt(2 ** (1 / 3) - 1)
        return (wc**2 / (wc**2 + w**2)) ** 3

    chain = power(kinematics_cutoff_hz) * power(cutoff_hz)
    level = np.array([np.max(2 * dt_s * w ** (2 * c) * chain) for c in range(3)])
    return level / (2 * dt_s * update_every * gains**2)


# --------------------------------------------------------------- the momentum chain's noise
# The chain's kernels (``chain_kernels`` rows): (input kind, rate-filter output, slow output).
# A held channel (the IMU's period means: gyro, accelerometer) enters the balance through the
# rate filter's value only; a point channel (the encoders) through its value (q) and its
# derivative (qd). The momentum form reads its P channels out of the slow filter's derivative and
# its Q channels out of its value (``momentum``).
CHAIN_KERNELS = (
    ("held", "value", "value"),
    ("held", "value", "derivative"),
    ("point", "value", "value"),
    ("point", "value", "derivative"),
    ("point", "derivative", "value"),
    ("point", "derivative", "derivative"),
)
# With the time-weighted twins of ``time_weighted_kernels`` (rows 6 to 11): each channel's
# kernels, then their twins.
HELD_EXTENDED, POINT_EXTENDED = np.array([0, 1, 6, 7]), np.array([2, 3, 4, 5, 8, 9, 10, 11])


@functools.lru_cache(maxsize=16)
def chain_kernels(
    dt_s: float,
    rate_cutoff_hz: float,
    product_cutoff_hz: float,
    cutoff_hz: float,
    regressor_every: int,
    n_delays: float = 10.0,
) -> np.ndarray:
    """Impulse responses K (6, span) of the momentum chain (``CHAIN_KERNELS``): K[r, m] is the
    slow filter's output r at one of its samples per unit impulse m control steps earlier on one
    input channel.

    The chain, as the estimator runs it (``preprocess.Preprocessor``, ``per_step``): the rate
    filter (``rate_cutoff_hz``; held channels with a zero-order hold of the new sample, point
    channels with a first-order hold), a momentum-form sample of its value and derivative every
    step, the product filter (``product_cutoff_hz``) every step, and the slow filter
    (``cutoff_hz``, period ``regressor_every`` steps) on the product filter's value, read out as
    value and derivative. Linear: the noise of an output at a slow sample is sum_m K[m] e_-m for
    white input e. Exact up to the truncation after ``n_delays`` of the chain's delays (the
    responses have decayed by then). Cached, read-only."""
    if regressor_every < 1:
        raise ValueError(f"regressor_every must be >= 1, got {regressor_every}")
    delays = [StateVariableFilter(1, dt_s, f).delay_s for f in (rate_cutoff_hz, product_cutoff_hz)]
    delays.append(StateVariableFilter(1, dt_s * regressor_every, cutoff_hz).delay_s)
    span = int(np.ceil(n_delays * sum(delays) / dt_s))
    span += regressor_every - span % regressor_every  # output at a slow-filter sample
    # Channel block 0: a held input; block 1: a point input (impulse at step k in column k).
    rate = StateVariableFilter(2 * span, dt_s, rate_cutoff_hz, held=slice(0, span))
    product = StateVariableFilter(3 * span, dt_s, product_cutoff_hz)
    slow = StateVariableFilter(3 * span, dt_s * regressor_every, cutoff_hz)
    for f in (rate, product, slow):  # a first sample sets the state: start at rest at zero
        f.step(np.zeros(f.n_channels))
    out = (np.zeros(3 * span), np.zeros(3 * span))
    for k in range(span + 1):
        impulse = np.zeros(2 * span)
        if k < span:
            impulse[[k, span + k]] = 1.0
        y, yd, _ = rate.step(impulse)
        value, _, _ = product.step(np.concatenate((y[:span], y[span:], yd[span:])))
        if k % regressor_every == 0:
            v, d, _ = slow.step(value)
            out = (v, d)
    # Output after step span: column k is the impulse span - k steps earlier; order m = 0, 1, ...
    v, d = (x.reshape(3, span)[:, ::-1] for x in out)
    kernels = np.stack([v[0], d[0], v[1], d[1], v[2], d[2]])
    kernels.setflags(write=False)
    return kernels


def time_weighted_kernels(kernels: np.ndarray, dt_s: float, at_s: float) -> np.ndarray:
    """The kernels and their time-weighted twins (2 r, span): K[r, m] and (at - m dt) K[r, m].
    A map that drifts over the chain's memory, J(t) = J(t0) + (t - t0) J', carries white noise
    e to sum_m J(t - m dt) K[m] e_-m = J(t0) (K * e) + J' (K_t * e) with t0 = t - ``at_s``: the
    twin is the kernel of the map's rate J' (s per unit)."""
    lag_s = at_s - dt_s * np.arange(kernels.shape[1])
    out = np.vstack((kernels, lag_s * kernels))
    out.setflags(write=False)
    return out


def kernel_lag_covariances(kernels: np.ndarray, update_every: int, n_lags: int) -> np.ndarray:
    """G (n_lags + 1, r, r): G[L, a, b] = sum_m K_a[m] K_b[m + L update_every], the covariance of
    outputs a at one update and b L updates later per unit white input variance."""
    span = kernels.shape[1]
    out = np.zeros((n_lags + 1, kernels.shape[0], kernels.shape[0]))
    for lag in range(n_lags + 1):
        shift = lag * update_every
        if shift < span:
            out[lag] = kernels[:, : span - shift] @ kernels[:, shift:].T
    return out


@njit(cache=True)
def lag_weighted_covariance(lag_cov: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """W = G(0) + sum_L>=1 rho(L) (G(L) + G(L)^T), symmetric: the per-update covariance at which
    a sequential filter must weigh updates whose noise is correlated as G(L) when its regressor's
    autocorrelation is rho(L) (rho(0) = 1). For a scalar regressor a_i and noise covariance
    C(i - j) the estimate sum a_i z_i / sum a_i^2 has the variance
    sum_ij a_i a_j C(i - j) / (sum a_i^2)^2 = W / sum a_i^2 exactly: the filter is consistent
    with the white measurement covariance W. For a regressor slow against the noise (rho = 1)
    W is the long-run covariance sum_L C(L) (the noise's spectral density at zero frequency);
    for noise read out of a derivative it is the spectral density averaged over the regressor's
    spectrum, (2 pi f)^2 S(f) at the regressor's rms frequency f. ``lag_cov`` (n_lags + 1, c, c),
    ``rho`` (n_lags + 1,); W (c, c), each entry summed over L in order. An entry of W depends on
    the same entries of the G(L) only: W of a sub-block of the channels is that sub-block of W."""
    n_lags, c = lag_cov.shape[0] - 1, lag_cov.shape[1]
    w = np.empty((c, c))
    for a in range(c):
        for b in range(c):
            weighted = 0.0
            for lag in range(1, n_lags + 1):
                weighted += rho[lag] * (lag_cov[lag, a, b] + lag_cov[lag, b, a])
            w[a, b] = lag_cov[0, a, b] + weighted
    return 0.5 * (w + w.T)


@njit(cache=True)
def psd_factor(w: np.ndarray) -> np.ndarray:
    """F = U diag(sqrt(max(s, 0))) with F F^T = W for a symmetric W = U diag(s) U^T, negative
    eigenvalues (round-off of a weighted sum of lag covariances with an estimated
    autocorrelation) set to zero; compiled (numba's eigh is the same LAPACK routine as numpy's)."""
    s, u = np.linalg.eigh(w)
    return u * np.sqrt(np.clip(s, 0.0, None))


@njit(cache=True)
def _add_regressor(cross, power, ring, ring_power, ring_index, index, a):
    """``RegressorAutocorrelation.add``'s sums, in place: the regressor ``a`` (6, 10) of update
    ``index``, per column k its power sum_r a_rk^2 into lag 0 and, for each ring slot L updates
    back (0 < L <= n_lags), the cross sum_r ring_rk a_rk into ``cross[L]`` and the pair's mean
    power into ``power[L]``; then ``a`` into the ring (slot ``index`` mod n_lags)."""
    n_lags = cross.shape[0] - 1
    n_rows, n_cols = a.shape
    own = np.zeros(n_cols)
    for r in range(n_rows):
        own += a[r] * a[r]
    cross[0] += own
    power[0] += own
    for slot in range(ring.shape[0]):
        lag = index - ring_index[slot]
        if 0 < lag <= n_lags:
            for k in range(n_cols):  # sum_r ring_rk a_rk, in row order
                pair = 0.0
                for r in range(n_rows):
                    pair += ring[slot, r, k] * a[r, k]
                cross[lag, k] += pair
                power[lag, k] += 0.5 * (own[k] + ring_power[slot, k])
    if n_lags:
        slot = index % n_lags
        ring[slot], ring_power[slot], ring_index[slot] = a, own, index


@njit(cache=True)
def autocorrelation_of(power: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """``RegressorAutocorrelation.rho`` from its sums (n_lags + 1, 10): over the columns k with
    power at lag 0, the mean of cross(L, k) / power(L, k) over those with power at lag L (0 for
    the others, which count in the sum but not in the mean's count); a lag none has power at
    takes the longest lag below it that has (lag 0 at worst); rho(0) = 1. No column with power:
    ones."""
    n = power.shape[0]
    rho = np.ones(n)
    mean = np.empty(n)
    last = 0  # the longest lag so far with a column counted
    for lag in range(n):
        total, counted, any_column = 0.0, 0, False
        for k in range(power.shape[1]):
            if power[0, k] > 0:
                any_column = True
                if power[lag, k] > 0:
                    total += cross[lag, k] / power[lag, k]
                    counted += 1
        if not any_column:
            return rho
        mean[lag] = total / max(counted, 1)
        if counted > 0:
            last = lag
        if lag > 0:
            rho[lag] = mean[last]
    return rho


class RegressorAutocorrelation:
    """The regressor's autocorrelation over update lags, rho(L) (n_lags + 1,), accumulated over a
    run: per parameter column k, rho_k(L) = sum_i <A_i,k, A_i-L,k> over the pairs L updates
    apart, normalised by those pairs' mean power, then averaged over the columns with power (each
    parameter counts alike, whatever its units). Lags not yet seen take the longest seen lag's
    value (one update seen: rho = 1, a slow regressor). The last ``n_lags`` regressors are kept
    in a ring (row ``index`` mod n_lags)."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(self, n_lags: int) -> None:
        self.n_lags = int(n_lags)
        self._cross = np.zeros((self.n_lags + 1, 10))
        self._power = np.zeros((self.n_lags + 1, 10))
        self._ring = np.zeros((max(self.n_lags, 1), 6, 10))
        self._ring_power = np.zeros((max(self.n_lags, 1), 10))
        self._ring_index = np.full(max(self.n_lags, 1), -(10**9), dtype=np.int64)

    def add(self, index: int, regressor: np.ndarray) -> None:
        """Account for the regressor (6, 10) of update ``index`` (update counts, increasing)."""
        _add_regressor(self._cross, self._power, self._ring, self._ring_power, self._ring_index,
                       int(index), _float(regressor))  # fmt: skip

    def rho(self) -> np.ndarray:
        """rho(L) (n_lags + 1,), rho(0) = 1 (``autocorrelation_of``)."""
        return autocorrelation_of(self._power, self._cross)
