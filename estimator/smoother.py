"""Fixed-lag smoother of a robot base's acceleration from its accelerometer and its position fixes.

Frames and units: world axes W (the module), m, m/s, m/s^2, s. Per world axis (the three are
independent and share one covariance: the noises are isotropic and the fixes simultaneous) the
state is the base origin's position and velocity x = (p, v). The accelerometer's reading of
control period k, rotated into world axes with the attitude and with the IMU's lever removed, is
the mean acceleration over the period plus white noise, u_k = a_k + n_k, n_k ~ N(0, sigma_a^2);
it drives the state over the period (exact for a constant acceleration within it):

    x_k = F x_k-1 + B a_k = F x_k-1 + B u_k + w_k,   F = [[1, dt], [0, 1]],  B = [dt^2 / 2, dt],
    w_k = -B n_k,  Q = sigma_a^2 B B^T;

a localization fix is y_k = p_k + e_k, e_k ~ N(0, sigma_p^2). A Kalman filter runs forward; the
Rauch-Tung-Striebel pass runs backward over the last ``lag`` periods:

    x_k-1|N = x_k-1|k-1 + C_k (x_k|N - x_k|k-1),   C_k = P_k-1|k-1 F^T P_k|k-1^-1,

and the smoothed acceleration is the reading minus the smoothed noise. From the two lines above,
x_k|N - F x_k-1|N - B u_k = Q P_k|k-1^-1 (x_k|N - x_k|k-1), which lies along B, so

    a_k|N = u_k + sigma_a^2 B^T P_k|k-1^-1 (x_k|N - x_k|k-1) = (v_k|N - v_k-1|N) / dt.

What it gains (``fused_psd_ratio``): for a lag long against 1 / (2 pi f_x) the smoother is the
non-causal Wiener filter of the two measurements of the acceleration, the accelerometer (two-sided
PSD S_a = sigma_a^2 dt) and the fixes differentiated twice (S_l(f) = sigma_p^2 T (2 pi f)^4, T the
fixes' period), so its error has the PSD

    S_fused(f) = S_a S_l / (S_a + S_l) = S_a / (1 + (f_x / f)^4),
    f_x = (S_a / (sigma_p^2 T))^(1/4) / (2 pi)                 (``crossover_hz``),

the accelerometer's white noise above f_x, the fixes' below. ``nominal`` (1e-3 m/s^2 at 62.5 Hz,
5 mm every 0.32 s): f_x = 0.034 Hz. The smoother knows nothing of the cargo: it sharpens the
motion the balance is built from, not the balance.

The lag it needs: the correction (smoothed less read acceleration) lives below f_x, so a lag
short against 1 / (2 pi f_x) = 4.7 s loses it. ``lagged_error_psd_ratio`` gives the error PSD at
any lag (``nominal``, at 0.02, 0.034 and 0.05 Hz: 0.98 / 1.00 / 1.00 of S_a at a 1 s lag,
0.30 / 0.66 / 0.91 at 8 s, 0.11 / 0.51 / 0.83 at 16 s, the Wiener values). The attitude that
rotates the readings into world axes costs nothing measurable: the gyro's integrated angle
(2e-4 rad/s per sample) and 0.2 deg fixes give an angle error PSD near 5e-9 rad^2/Hz at 0.06 Hz,
times accelerations <= 0.02 m/s^2 four orders of magnitude under S_a.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def crossover_hz(
    accel_std: float, dt_s: float, position_std_m: float, fix_period_s: float
) -> float:
    """f_x (Hz) where the fixes' twice-differentiated noise equals the accelerometer's (module
    docstring): (sigma_a^2 dt / (sigma_p^2 T))^(1/4) / (2 pi)."""
    values = (accel_std, dt_s, position_std_m, fix_period_s)
    if not all(np.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"accel_std, dt_s, position_std_m, fix_period_s must be > 0: {values}")
    return float((accel_std**2 * dt_s / (position_std_m**2 * fix_period_s)) ** 0.25 / (2 * np.pi))


def fused_psd_ratio(freq_hz, crossover: float) -> np.ndarray:
    """S_fused(f) / S_a = 1 / (1 + (f_x / f)^4) (module docstring): the smoothed acceleration's
    error PSD over the accelerometer's, at ``freq_hz`` (Hz, > 0)."""
    ratio = (np.asarray(freq_hz, dtype=float) / crossover) ** 4
    return ratio / (1.0 + ratio)


def transition(dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """F (2, 2) and B (2,) of one control period (module docstring)."""
    return np.array([[1.0, dt_s], [0.0, 1.0]]), np.array([0.5 * dt_s**2, dt_s])


@njit(cache=True)
def kalman_step(x, p, u, fix, has_fix, f, b, q, pos_var):
    """One period of the forward filter, all axes at once: x (2, 3) and P (2, 2) at k-1 -> the
    prediction (x_k|k-1, P_k|k-1) and the filtered (x_k|k, P_k|k) with the fix y_k = ``fix``
    (3,) when ``has_fix``: K = P H^T / (H P H^T + sigma_p^2), H = [1, 0]."""
    x_pred = f @ x + np.outer(b, u)
    p_pred = f @ p @ f.T + q
    if not has_fix:
        return x_pred, p_pred, x_pred.copy(), p_pred.copy()
    gain = p_pred[:, 0] / (p_pred[0, 0] + pos_var)
    x_filt = x_pred + np.outer(gain, fix - x_pred[0])
    p_filt = p_pred - np.outer(gain, p_pred[0])
    return x_pred, p_pred, x_filt, 0.5 * (p_filt + p_filt.T)


@njit(cache=True)
def kalman_record(u, fixes, has_fix, x0, p0, f, b, q, pos_var):
    """``kalman_step`` over a record (u, fixes (n, 3), has_fix (n,)) from the state x0 (2, 3),
    P0 (2, 2) of period 0: predictions and filtered states and covariances (n, 2, 3), (n, 2, 2),
    period 0's both x0, P0."""
    n = u.shape[0]
    x_pred, x_filt = np.empty((n, 2, 3)), np.empty((n, 2, 3))
    p_pred, p_filt = np.empty((n, 2, 2)), np.empty((n, 2, 2))
    x_pred[0], x_filt[0], p_pred[0], p_filt[0] = x0, x0, p0, p0
    for k in range(1, n):
        step = kalman_step(x_filt[k - 1], p_filt[k - 1], u[k], fixes[k], has_fix[k], f, b, q,
                           pos_var)  # fmt: skip
        x_pred[k], p_pred[k], x_filt[k], p_filt[k] = step
    return x_pred, p_pred, x_filt, p_filt


@njit(cache=True)
def rts_gain(p_filt_prev, p_pred, f):
    """C_k = P_k-1|k-1 F^T P_k|k-1^-1 (2, 2): the RTS gain of period k (module docstring)."""
    return p_filt_prev @ f.T @ np.linalg.inv(p_pred)


@njit(cache=True)
def rts_states(x_pred, x_filt, gains):
    """Backward RTS pass over a window of n periods (x_* (n, 2, 3), ``gains`` C_k (n, 2, 2),
    C_0 unused): the smoothed states x_k|N (n, 2, 3). The smoothed accelerations are their
    velocities' differences, a_k|N = (v_k|N - v_k-1|N) / dt (module docstring)."""
    n = x_pred.shape[0]
    x_s = np.empty_like(x_filt)
    x_s[n - 1] = x_filt[n - 1]
    for k in range(n - 1, 0, -1):
        # x_k-1|N = x_k-1|k-1 + C_k (x_k|N - x_k|k-1), the product in loops (no temporaries:
        # the pass runs once per control step over the whole lag).
        for i in range(2):
            for j in range(3):
                acc = x_filt[k - 1, i, j]
                for m in range(2):
                    acc += gains[k, i, m] * (x_s[k, m, j] - x_pred[k, m, j])
                x_s[k - 1, i, j] = acc
    return x_s


def smooth_record(
    u_world: np.ndarray,
    fixes_world: np.ndarray,
    has_fix: np.ndarray,
    dt_s: float,
    accel_std: float,
    position_std_m: float,
    velocity_std_mps: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The whole record at once (fixed-interval smoother): readings u (n, 3), fixes (n, 3) where
    ``has_fix`` (n,); the first period must hold a fix (it starts the filter, velocity
    N(0, ``velocity_std_mps``^2)). Returns the smoothed states (n, 2, 3) and the smoothed
    accelerations of periods 1..n-1 (n - 1, 3)."""
    u, fixes = np.asarray(u_world, dtype=float), np.asarray(fixes_world, dtype=float)
    has_fix = np.asarray(has_fix, dtype=bool)
    if u.ndim != 2 or u.shape[1] != 3 or fixes.shape != u.shape or has_fix.shape != u.shape[:1]:
        raise ValueError(f"u (n, 3), fixes (n, 3), has_fix (n,): {u.shape}, {fixes.shape}")
    if not has_fix[0]:
        raise ValueError("the first period must hold a fix (it starts the filter)")
    f, b = transition(dt_s)
    q, pos_var = accel_std**2 * np.outer(b, b), position_std_m**2
    x0, p0 = np.vstack((fixes[0], np.zeros(3))), np.diag([pos_var, velocity_std_mps**2])
    x_pred, p_pred, x_filt, p_filt = kalman_record(u, fixes, has_fix, x0, p0, f, b, q, pos_var)
    gains = np.zeros_like(p_pred)
    for k in range(1, len(gains)):
        gains[k] = rts_gain(p_filt[k - 1], p_pred[k], f)
    x_s = rts_states(x_pred, x_filt, gains)
    return x_s, np.diff(x_s[:, 1], axis=0) / dt_s


class FixedLagSmoother:
    """Online fixed-lag smoother of one base's world-axes acceleration (module docstring).

    ``step(u_world, fix_world)`` runs the forward filter over one control period: its
    accelerometer reading in world axes (3,) (m/s^2, the base origin's) and the position fix of
    its end (3,) m, or None. ``lagged_acceleration()`` runs the backward pass over the window and
    returns the smoothed acceleration of the period ``lag_steps`` back (3,), or None until that
    many periods have passed: call it only where it is needed (an update instant), it costs
    O(lag). The first fix starts the filter (position at the fix, velocity
    N(0, ``velocity_std_mps``^2)); readings before it are dropped.
    """

    def __init__(
        self,
        dt_s: float,
        accel_std: float,
        position_std_m: float,
        lag_steps: int,
        velocity_std_mps: float = 1.0,
    ) -> None:
        values = (dt_s, accel_std, position_std_m, velocity_std_mps)
        if not all(np.isfinite(v) and v > 0 for v in values):
            raise ValueError(
                f"dt_s, accel_std, position_std_m, velocity_std_mps must be > 0: {values}"
            )
        if lag_steps < 1:
            raise ValueError(f"lag_steps must be >= 1, got {lag_steps}")
        self.dt_s, self.lag_steps = float(dt_s), int(lag_steps)
        self.f, self.b = transition(self.dt_s)
        self.q = accel_std**2 * np.outer(self.b, self.b)
        self.pos_var = float(position_std_m**2)
        self.velocity_var = float(velocity_std_mps**2)
        # Ring buffers of x_k|k-1, x_k|k and the RTS gain C_k over the last lag + 2 periods (the
        # oldest one's smoothed velocity is the start of the returned period's); the newest
        # P_k|k starts the next period.
        n = self.lag_steps + 2
        self._x_pred, self._x_filt = np.zeros((n, 2, 3)), np.zeros((n, 2, 3))
        self._gain = np.zeros((n, 2, 2))
        self._p = np.zeros((2, 2))
        self.periods = 0  # periods in the window since the first fix
        self._last = -1  # the newest entry's slot

    def step(self, u_world: np.ndarray, fix_world: np.ndarray | None) -> None:
        u = np.asarray(u_world, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"u_world must be 3 finite numbers, got {u_world!r}")
        if self.periods == 0:
            if fix_world is None:
                return
            x = np.vstack((np.asarray(fix_world, dtype=float), np.zeros(3)))
            self._store(x, x, np.zeros((2, 2)))
            self._p = np.diag([self.pos_var, self.velocity_var])
            return
        fix = np.zeros(3) if fix_world is None else np.asarray(fix_world, dtype=float)
        x_pred, p_pred, x_filt, p_filt = kalman_step(
            self._x_filt[self._last], self._p, u, fix, fix_world is not None, self.f, self.b,
            self.q, self.pos_var,
        )  # fmt: skip
        self._store(x_pred, x_filt, rts_gain(self._p, p_pred, self.f))
        self._p = p_filt

    def _store(self, x_pred, x_filt, gain) -> None:
        self._last = (self._last + 1) % self._x_pred.shape[0]
        k = self._last
        self._x_pred[k], self._x_filt[k], self._gain[k] = x_pred, x_filt, gain
        self.periods += 1

    def window_accelerations(self) -> np.ndarray | None:
        """The smoothed accelerations (m, 3) of the window's periods, newest last, every one
        smoothed on all the data so far (fixed-interval smoothing of the tail: m = lag_steps + 1,
        fewer while the window fills), or None before two periods."""
        n = min(self.periods, self._x_pred.shape[0])
        if n < 2:
            return None
        order = (self._last + 1 + np.arange(n) - n) % self._x_pred.shape[0]  # oldest first
        x_s = rts_states(self._x_pred[order], self._x_filt[order], self._gain[order])
        return np.diff(x_s[:, 1], axis=0) / self.dt_s

    def lagged_acceleration(self) -> np.ndarray | None:
        """The smoothed acceleration (3,) of the period ``lag_steps`` back, or None."""
        n = self._x_pred.shape[0]
        if self.periods < n:
            return None
        order = (self._last + 1 + np.arange(n)) % n  # oldest first
        x_s = rts_states(self._x_pred[order], self._x_filt[order], self._gain[order])
        return (x_s[1, 1] - x_s[0, 1]) / self.dt_s


def lagged_error_psd_ratio(
    freq_hz: np.ndarray,
    lag_steps: int,
    dt_s: float,
    accel_std: float,
    position_std_m: float,
    fix_every: int,
    settle_steps: int = 2500,
) -> np.ndarray:
    """S_e(f) / S_a of ``FixedLagSmoother`` at ``lag_steps`` in its steady state (the fixes'
    schedule repeats every ``fix_every`` periods, so the error is cyclostationary; this is its
    time-averaged PSD): with g_p the error's response to a unit accelerometer error at phase p of
    the schedule and h its response to a unit fix error, both found by running the smoother on
    them (linear; its gains do not depend on the data),

        S_e(f) = dt (sigma_a^2 mean_p |G_p(f)|^2 + sigma_p^2 |H(f)|^2 / fix_every),
        G_p(f) = sum_j g_p[j] exp(-2 pi i f j dt).

    Tends to ``fused_psd_ratio`` as the lag grows (the non-causal Wiener filter), to 1 with no
    lag. ``settle_steps``: periods run on zero data first (the covariances settle) and after the
    impulse (its response dies out)."""
    freq = np.asarray(freq_hz, dtype=float)
    power = np.zeros_like(freq)
    impulses = [(phase, False) for phase in range(fix_every)] + [(0, True)]
    for phase, in_fix in impulses:
        response = _impulse_response(
            lag_steps, dt_s, accel_std, position_std_m, fix_every, settle_steps, phase, in_fix
        )
        j = np.arange(response.size) - settle_steps  # periods after the impulse's
        spectrum = np.abs(np.exp(-2j * np.pi * np.outer(freq, j * dt_s)) @ response) ** 2
        weight = position_std_m**2 / fix_every if in_fix else accel_std**2 / fix_every
        power += weight * spectrum
    return power / accel_std**2


def _impulse_response(lag_steps, dt_s, accel_std, position_std_m, fix_every, settle_steps,
                      phase, in_fix) -> np.ndarray:  # fmt: skip
    """The lagged accelerations' response (x axis) to a unit error in the reading of period
    m = phase + the first multiple of ``fix_every`` from 2 settle_steps (``in_fix`` False) or
    in the fix of period m (True, a fix period), for periods m - settle_steps .. m +
    settle_steps."""
    smoother = FixedLagSmoother(dt_s, accel_std, position_std_m, lag_steps)
    impulse = fix_every * -(-2 * settle_steps // fix_every) + phase  # phase 0 holds a fix
    out = []
    for k in range(impulse + settle_steps + lag_steps + 1):
        u, fix = np.zeros(3), np.zeros(3) if k % fix_every == 0 else None
        if k == impulse:
            if in_fix:
                fix[0] = 1.0
            else:
                u[0] = 1.0
        smoother.step(u, fix)
        if k - lag_steps >= impulse - settle_steps:
            out.append(smoother.lagged_acceleration()[0])
    return np.array(out)
