"""The momentum chain's sample Jacobian and the sensor-noise modes of an update instant
(``noise_model.NoiseModel.momentum_jacobians``; the chain and its kernels: ``motion``).

The momentum-form sample (``momentum``) is differentiated with respect to the rate filter's
outputs by forward differences (``sample_jacobian``), at two points along the pre-filter's
derivatives for its drift (``drifting_sample_jacobian``); its columns, read out of the slow
filter's value and derivative, times each sensor channel's factor give the modes
(``momentum_noise_modes``, ``instant_noise_modes``). The differences are taken in one scratch
per instant (``jacobian_work``) on ``momentum``'s ``_into`` forms, which allocate nothing."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from .momentum import (
    CARGO_P,
    CARGO_P_MAP,
    CARGO_Q,
    CARGO_Q_MAP,
    LINKS_P,
    LINKS_Q,
    SIZE,
    THRUST,
    LinkGeometry,
    MomentumWork,
    geometry_work,
    link_geometry_into,
    momentum_at_into,
    momentum_work,
)

_CARGO_Q_MAP_T = np.ascontiguousarray(CARGO_Q_MAP.T)  # ``instant_noise_modes``' squared rates


class JacobianWork(NamedTuple):
    """Scratch of the sample's Jacobians (``jacobian_work``), so that ``sample_jacobian_into``
    and ``drifting_jacobians_into`` allocate nothing."""

    xs: np.ndarray  # (1 + n_x, n_x): x (row 0), x with its entry k stepped (row 1 + k)
    samples: np.ndarray  # (1 + n_x, SIZE): the sample at each row of xs
    momentum: MomentumWork  # of 1 + n_x rows (the rows at the angles' geometry)
    geo: LinkGeometry  # the arrays of the angles' geometry (``momentum.geometry_work``)
    value: np.ndarray  # (12 + nj,) the pre-filter's value moved along its derivative
    rate: np.ndarray  # (12 + nj,) and its derivative
    sides: np.ndarray  # (2, SIZE, n_x): J- and J+ (``drifting_jacobians_into``)


@njit(cache=True)
def jacobian_work(n_links, n_joints):
    """A ``JacobianWork`` for a robot of ``n_links`` links and ``n_joints`` joints."""
    n_x = 6 + 2 * n_joints
    return JacobianWork(
        np.empty((1 + n_x, n_x)), np.empty((1 + n_x, SIZE)),
        momentum_work(n_links, 1 + n_x, n_joints), geometry_work(n_links),
        np.empty(12 + n_joints), np.empty(12 + n_joints), np.empty((2, SIZE, n_x)),
    )  # fmt: skip


@njit(cache=True)
def sample_jacobian(arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, step=1e-6):
    """d sample / dx (``momentum.SIZE``, 6 + 2 nj) of the momentum-form sample
    (``momentum.momentum_pass``, here ``momentum_at`` with the joint angles' geometry computed
    once and again only for their own steps) with respect to the rate filter's outputs
    x = (gyro (3) rad/s, the IMU point's acceleration (3) m/s^2, q (nj) rad, qd (nj) rad/s), base
    frame, by forward differences of ``step``: the sample is quadratic in the rates and the
    acceleration, so the error is ``step`` times the quadratic coefficient (relative 1e-6 at the
    robot's scale), O(step) for the angles. In the scratch of ``jacobian_work``
    (``sample_jacobian_into``)."""
    nj = q.shape[0]
    jac = np.empty((SIZE, 6 + 2 * nj))
    work = jacobian_work(arrays.parent.shape[0], nj)
    sample_jacobian_into(jac, work, arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, step)
    return jac


@njit(cache=True, inline="always")
def _motion_rows_into(work, xs, rows):
    """The motion of ``rows`` of ``xs`` (gyro, acceleration, q, qd) into ``work``'s
    (``MomentumWork``) first rows of base rates, accelerations and joint rates."""
    nj = (xs.shape[1] - 6) // 2
    for r in range(rows.shape[0]):
        x = xs[rows[r]]
        for i in range(3):
            work.w_rows[r, i] = x[i]
            work.acc_rows[r, i] = x[3 + i]
        for j in range(nj):
            work.qd_rows[r, j] = x[6 + nj + j]


@njit(cache=True, inline="always")
def sample_jacobian_into(jac, work, arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, step):
    """``sample_jacobian`` into ``jac`` (``SIZE``, 6 + 2 nj), ``work`` (``jacobian_work``) as
    scratch: J[:, k] = (sample(x + step e_k) - sample(x)) / step."""
    nj = q.shape[0]
    n_x = 6 + 2 * nj
    xs, samples, mw = work.xs, work.samples, work.momentum
    for i in range(3):
        xs[0, i], xs[0, 3 + i] = w_base[i], acc_imu[i]
    for j in range(nj):
        xs[0, 6 + j], xs[0, 6 + nj + j] = q[j], qd[j]
    for r in range(1, 1 + n_x):
        xs[r] = xs[0]
        xs[r, r - 1] += step
    # One batch of the rows at the angles' geometry (x and the steps of all but the angles),
    # then the angles' own rows at theirs.
    at_q = np.arange(7 + nj)
    at_q[7:] += nj
    geo = link_geometry_into(work.geo, arrays, q, mw.vec, mw.mat)
    _motion_rows_into(mw, xs, at_q)
    n = at_q.shape[0]
    momentum_at_into(mw.rows[:n], arrays, imu_pos, geo, mw.w_rows[:n], mw.acc_rows[:n],
                     mw.qd_rows[:n], thrust_base, mw)  # fmt: skip
    for r in range(n):
        samples[at_q[r]] = mw.rows[r]
    for k in range(6, 6 + nj):
        geo_k = link_geometry_into(work.geo, arrays, xs[1 + k, 6 : 6 + nj], mw.vec, mw.mat)
        _motion_rows_into(mw, xs, np.array([1 + k]))
        momentum_at_into(mw.rows[:1], arrays, imu_pos, geo_k, mw.w_rows[:1], mw.acc_rows[:1],
                         mw.qd_rows[:1], thrust_base, mw)  # fmt: skip
        samples[1 + k] = mw.rows[0]
    for c in range(SIZE):
        for k in range(n_x):
            jac[c, k] = (samples[1 + k, c] - samples[0, c]) / step


@njit(cache=True)
def drifting_sample_jacobian(arrays, imu_pos, state, n_joints, step_s):
    """``sample_jacobian`` J (``SIZE``, 6 + 2 nj) at the rate filter's motion x and its time
    derivative dJ/dt (1/s), from the pre-filter's state (3, 12 + nj) over [gyro_B (rad/s), the
    IMU point's acceleration_B (m/s^2), q (rad), thrust_B] (value, derivative, second
    derivative): x = (gyro, acceleration, q, qd = q's derivative, thrust) at the state, and from
    J+- = J(x +- step_s x' / 2) along the state's derivatives, J = (J+ + J-) / 2 and
    dJ/dt = (J+ - J-) / step_s (central, second order in step_s)."""
    jacs = _drifting_jacobians(arrays, imu_pos, state, n_joints, step_s)
    return jacs[0], jacs[1]


@njit(cache=True)
def _drifting_jacobians(arrays, imu_pos, state, n_joints, step_s):
    """``drifting_sample_jacobian``'s J and dJ/dt stacked (2, ``SIZE``, 6 + 2 nj)."""
    jacs = np.empty((2, SIZE, 6 + 2 * n_joints))
    work = jacobian_work(arrays.parent.shape[0], n_joints)
    drifting_jacobians_into(jacs, work, arrays, imu_pos, state, n_joints, step_s)
    return jacs


@njit(cache=True)
def drifting_jacobians_into(jacs, work, arrays, imu_pos, state, n_joints, step_s):
    """``_drifting_jacobians`` into ``jacs`` (2, ``SIZE``, 6 + 2 nj), ``work``
    (``jacobian_work``) as scratch: J+- at the state moved by +- step_s / 2 along its
    derivatives (value x + s x', derivative x' + s x''), J = (J+ + J-) / 2,
    dJ/dt = (J+ - J-) / step_s."""
    nj = n_joints
    value, rate, sides = work.value, work.rate, work.sides
    for k in range(2):
        sign = -0.5 if k == 0 else 0.5
        for i in range(value.shape[0]):
            value[i] = state[0, i] + sign * step_s * state[1, i]
            rate[i] = state[1, i] + sign * step_s * state[2, i]
        q, qd, thrust = value[6 : 6 + nj], rate[6 : 6 + nj], value[6 + nj :]
        sample_jacobian_into(sides[k], work, arrays, imu_pos, value[0:3], value[3:6], q, qd,
                             thrust, 1e-6)  # fmt: skip
    for c in range(SIZE):
        for k in range(sides.shape[2]):
            jacs[0, c, k] = 0.5 * (sides[0, c, k] + sides[1, c, k])
            jacs[1, c, k] = (sides[1, c, k] - sides[0, c, k]) / step_s


@njit(cache=True)
def _readout_columns(jacs, p_map, q_map):
    """The balance's model-side noise n = d(links + Y pi - thrust) from the sample noise of each
    of ``jacs`` (2, ``SIZE``, c) (the Jacobian and its rate) read out of the slow filter's value
    (its thrust and Q channels) and derivative (its P channels;
    ``momentum.balance_from_filtered``): (4, 66, c), rows 0-5 d links - d thrust and rows 6-65
    d Y of the read-outs m = 2 j + (0 value, 1 derivative) of ``jacs[j]``; ``p_map``, ``q_map``
    the regressor's maps ``momentum.CARGO_P_MAP``, ``CARGO_Q_MAP``, each applied to both of
    ``jacs`` in one product."""
    n = jacs.shape[2]
    out = np.empty((4, 66, n))
    q_in, p_in = np.empty((9, 2 * n)), np.empty((6, 2 * n))
    for j in range(2):
        out[2 * j, :6] = jacs[j, LINKS_Q] - jacs[j, THRUST]
        out[2 * j + 1, :6] = jacs[j, LINKS_P]
        q_in[:, j * n : (j + 1) * n] = jacs[j, CARGO_Q]
        p_in[:, j * n : (j + 1) * n] = jacs[j, CARGO_P]
    q_out, p_out = q_map @ q_in, p_map @ p_in
    for j in range(2):
        out[2 * j, 6:] = q_out[:, j * n : (j + 1) * n]
        out[2 * j + 1, 6:] = p_out[:, j * n : (j + 1) * n]
    return out


@njit(cache=True)
def _factored_into(out_links, out_y, starts, readout, columns, factor):
    """Channels that share the factor F (m, m): channel c's read-out columns (``columns[c]``
    (m, 2): motion coordinate x, read-out m of ``_readout_columns``' (4, 66, c)) times F,
    written into its modes starts[c] ... starts[c] + m - 1 of ``out_links`` (6, n) and
    ``out_y`` (n, 60); one product for all of them (each row's the same as alone)."""
    n_chan, m = columns.shape[0], columns.shape[1]
    chan = np.empty((66 * n_chan, m))
    for c in range(n_chan):
        for a in range(m):
            chan[66 * c : 66 * (c + 1), a] = readout[columns[c, a, 1], :, columns[c, a, 0]]
    modes = chan @ factor
    for c in range(n_chan):
        start = starts[c]
        out_links[:, start : start + m] = modes[66 * c : 66 * c + 6]
        out_y[start : start + m] = modes[66 * c + 6 : 66 * (c + 1)].T


@njit(cache=True)
def _same_factor_end(factors, first):
    """The end of the run of factors (c, m, m) from ``first`` that are bit for bit
    ``factors[first]`` (such channels take one product in ``_factored_into``)."""
    bits = factors.view(np.int64)
    end = first + 1
    while end < factors.shape[0] and np.all(bits[end] == bits[first]):
        end += 1
    return end


@njit(cache=True)
def _noise_modes_into(out_links, out_y, jacs, n_joints, held_factors, point_factor, p_map,
                      q_map):  # fmt: skip
    """``_noise_modes`` written into the first 24 + 8 nj modes of ``out_links`` (6, n) and
    ``out_y`` (n, 60); the held channels that share a factor in one product."""
    nj = n_joints
    readout = _readout_columns(jacs, p_map, q_map)
    first = 0
    while first < 6:  # gyro x, y, z, accelerometer x, y, z: read-outs 0 ... 3
        end = _same_factor_end(held_factors, first)
        held = np.empty((end - first, 4, 2), dtype=np.int64)
        for c in range(first, end):
            held[c - first, :, 0] = c
            held[c - first, :, 1] = np.arange(4)
        starts = 4 * np.arange(first, end)
        _factored_into(out_links, out_y, starts, readout, held, held_factors[first])
        first = end
    point = np.empty((nj, 8, 2), dtype=np.int64)
    for i in range(nj):  # per encoder: (q, 0), (q, 1), (qd, 0), (qd, 1), then read-outs 2, 3
        for k in range(4):
            point[i, 2 * k : 2 * k + 2, 0] = 6 + i + (k % 2) * nj
            point[i, 2 * k, 1], point[i, 2 * k + 1, 1] = 2 * (k // 2), 2 * (k // 2) + 1
    starts = 24 + 8 * np.arange(nj)
    _factored_into(out_links, out_y, starts, readout, point, point_factor)


@njit(cache=True)
def _noise_modes(jacs, n_joints, held_factors, point_factor, p_map, q_map):
    """``momentum_noise_modes`` with the factors given: one per held channel (6, 4, 4), gyro
    x, y, z then accelerometer x, y, z, and one for every encoder (8, 8)."""
    n = 24 + 8 * n_joints
    links, y = np.empty((6, n)), np.empty((n, 60))
    _noise_modes_into(links, y, jacs, n_joints, held_factors, point_factor, p_map, q_map)
    return links, y.reshape(n, 6, 10)


@njit(cache=True)
def instant_noise_modes(arrays, imu_pos, state, n_joints, step_s, held_factors, point_factor,
                        rate_terms, rate_var, n_rate):  # fmt: skip
    """An update instant's sensor-noise modes (``NoiseModel.momentum_jacobians``) in one
    compiled call: d links - d thrust (6, n) and d Y (n, 6, 10) with n = 24 + 8 nj + ``n_rate``.

    The sample's Jacobian J and its drift dJ/dt at the pre-filter's ``state``
    (``drifting_sample_jacobian``, step ``step_s`` s) give the IMU's and the encoders' modes
    (``_noise_modes``: the chain's read-out columns times each channel's factor); then one mode
    per squared-rate term k of ``rate_terms`` (k, ``SIZE``) with variance v_k (``rate_var``):
    sqrt(v_k) (Q_links, M_Q Q_Y) (``momentum.CARGO_Q_MAP``). ``n_rate`` such modes always
    (zero columns without terms: k = 0), so that the count stays that of the variances."""
    jacs = _drifting_jacobians(arrays, imu_pos, state, n_joints, step_s)
    n_modes = 24 + 8 * n_joints
    if rate_terms.shape[0] != 0 and rate_terms.shape[0] != n_rate:
        raise ValueError("rate_terms must have 0 or n_rate rows")
    links = np.zeros((6, n_modes + n_rate))
    y = np.zeros((n_modes + n_rate, 60))
    _noise_modes_into(links, y, jacs, n_joints, held_factors, point_factor, CARGO_P_MAP,
                      CARGO_Q_MAP)  # fmt: skip
    if rate_terms.shape[0]:
        scaled = rate_terms * np.sqrt(rate_var).reshape(-1, 1)
        links[:, n_modes:] = np.ascontiguousarray(scaled[:, LINKS_Q]).T
        y[n_modes:] = np.ascontiguousarray(scaled[:, CARGO_Q]) @ _CARGO_Q_MAP_T
    return links, y.reshape(n_modes + n_rate, 6, 10)


def momentum_noise_modes(
    jac: np.ndarray,
    jac_rate: np.ndarray,
    n_joints: int,
    held_factor: np.ndarray | None = None,
    point_factor: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per sensor channel, the balance noise's columns per chain kernel and twin
    (``CHAIN_KERNELS``, ``time_weighted_kernels``), times the channel kind's factor F (F F^T
    the kernels' lag-weighted covariance; None: the identity, the columns themselves):
    (d links - d thrust (6, 24 + 8 nj), d Y (24 + 8 nj, 6, 10)) from the sample's Jacobian
    ``jac`` (``sample_jacobian``) and its time derivative ``jac_rate`` (1/s) (both from
    ``drifting_sample_jacobian``). Channel order:
    gyro (3), accelerometer (3) (held, 4 columns each: value->value, value->derivative, the same
    of ``jac_rate``), encoders (nj) (point, 8 each: q's two, qd's two, then the same of
    ``jac_rate``). Compiled (``_noise_modes``)."""
    held = np.eye(4) if held_factor is None else np.ascontiguousarray(held_factor, dtype=float)
    point = np.eye(8) if point_factor is None else np.ascontiguousarray(point_factor, dtype=float)
    jacs = np.stack((jac, jac_rate)).astype(float)
    held_factors = np.ascontiguousarray(np.broadcast_to(held, (6, 4, 4)))
    return _noise_modes(jacs, int(n_joints), held_factors, point, CARGO_P_MAP, CARGO_Q_MAP)
