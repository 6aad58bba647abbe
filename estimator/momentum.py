"""The wrench balance in momentum form: its products formed before the balance's filters.

Why. The balance (``rne``) is linear in the cargo's parameters pi but nonlinear in the motion:
rotations by the joint angles, products of rates. A linear filter H commutes with the first
(H[Y] pi = H[Y pi]) but not with the second (H[u v] != H[u] H[v]); filtering the signals before
the products (the 1 Hz pre-filter that also supplies the accelerations) leaves a model error that
grows with the harmonics of the motion (22 % of a principal moment at a 3 s servo period). Here
every quantity of the balance is written as

    Z(t) = d/dt P(t) + Q(t),

with P and Q functions of the positions, the rates and the measured acceleration of the IMU point
only (no angular or joint acceleration), evaluated at each sample (from the readings through a
fast filter, see Filters). A linear time-invariant filter H then gives H[Z] = H'[P] + H[Q]
exactly (H' its derivative output: d/dt H = H d/dt), whatever its cutoff.

Frames and units. B is the base frame, G the grasp frame (rigid with the cargo), I the IMU point
(rigid with the base). Every rate is inertial. ``R`` = R_BG maps G coordinates to B; a vector
with suffix G is in G coordinates (x_G = R^T x_B). For a vector X, D X denotes its inertial time
derivative; in the coordinates of G, which turns at w_G,

    (D X)_G = d/dt X_G + w_G x X_G.                                                       (1)

Velocities are taken relative to the frame that translates with I (no rotation): the velocity of
a point x is nu(x) = d/dt (x - x_I) (m/s, inertial), which needs no absolute velocity, and the
acceleration of x is a(x) = a_I + D nu(x), with a_I the accelerometer's reading (the IMU point's
acceleration; the cabin is in free fall). With rho = x - x_g from G's origin x_g:

Rate of change of momentum of rigid bodies k (mass m_k, centre of mass x_k, inertia I_k about it
in current orientation, angular velocity w_k), as a wrench about G's origin:

    f = sum m_k a(x_k) = D [sum m_k nu_k] + M a_I,
    n = sum D(I_k w_k) + rho_k x m_k a(x_k)
      = D [sum I_k w_k + m_k rho_k x nu_k] + (sum m_k rho_k) x a_I + nu_g x sum m_k nu_k,

using rho_k x D nu_k = D(rho_k x nu_k) - D rho_k x nu_k and D rho_k = nu_k - nu_g (nu_g: the
velocity of G's origin). With (1): P = [p; L] = [sum m_k nu_k; sum I_k w_k + m_k rho_k x nu_k]
in G (N s, N m s) and

    Q = [R^T M a_I; R^T ((sum m_k rho_k) x a_I + nu_g x p)] + [w_G x p_G; w_G x L_G].

For the robot's own links this gives ``links`` of ``rne.Balance``. For the cargo, rigid with G
(h = m c and I about G's origin constant in G), the same with nu(x) = nu_g + w x (x - x_g) gives
Y pi = d/dt (P_Y pi) + Q_Y pi with, in ``rne.body_regressor``'s form Y(acc, w, wd),

    P_Y = Y(nu_G, 0, w_G),     Q_Y = Y(c, w_G, 0),     c = R^T a_I + w_G x nu_G,

since Y is linear in acc and wd at w = 0, wd_G = d/dt w_G, and a_G = d/dt nu_G + c by (1). The
propulsion wrench in G is R-rotated and shifted, T_GB thrust_B, a sample product like the others.

Filters. A sample of P and Q needs the rates of the joints, which the encoders give only
through differences, and the raw difference (q_k - q_k-1) / dt carries 2^(1/2) s / dt of the
encoders' noise s (0.09 rad/s at 1 mrad and 62.5 Hz against 0.12 rad/s of servo rate). Q's
products of joint rates square it: in expectation var(qd) times Q at a unit joint rate, which
``momentum_sample`` subtracts given the variance, but its fluctuation enters the regressor and
the offset together and biases the fit (errors in variables: 10 % mass on the arm motion with the
encoders' noise alone). So the readings first pass a fast filter F (``Preprocessor``'s rate
filter, 8 Hz: the IMU's period means held, the encoders' points with a first-order hold, so its
outputs describe one instant), whose derivative gives the joint rates; P and Q are formed from
F's outputs. F does not commute with the products either, but its departure from a pure delay,
of order (f / f_F)^2, is small at 8 Hz for motion below 1 Hz. The samples of P and Q are then
low-passed (the pre-filter's cutoff, then the slow balance filter): linear from there on.

Channels. The cargo's P_Y and Q_Y (60 entries each) are fixed linear maps of few numbers:
P_Y = M_P [nu_G; w_G] (Y is linear in acc and wd), and, Y(c, w, 0) being linear in c and
quadratic in w, Q_Y = M_Q [c; w_x^2, w_y^2, w_z^2, w_x w_y, w_x w_z, w_y w_z] (``CARGO_P_MAP``,
``CARGO_Q_MAP``, (60, 6) and (60, 9)). A linear filter commutes with a constant map, H[M x] =
M H[x], so the filters run on those 6 + 9 numbers (``SIZE`` = 33 channels with the thrust's and
the links' 6 + 6 + 6) and the regressor is mapped out of the filtered ones exactly
(``balance_from_filtered``).

Servo ripple. The filters' chains are consistent for what they are given (a point sample with a
first-order hold and a period mean with a zero-order hold of the new sample both pass a slow
signal with gain sinc^2(w dt / 2)), but the motion between samples is not smooth: a servo target
T_k is held over the period, so the servo torque K_p (T_k - q(t)) - K_v qd steps by
K_p (T_k - T_k-1) at each sample instant and falls back linearly as q follows, a sawtooth of zero
mean on top of the smooth torque. Its response is inertia-dominated (62.5 Hz against a few rad/s
of servo bandwidth): a generalised acceleration ripple H^-1 [0; tau_saw] (H the free-floating mass
matrix of the robot and cargo, u = [v_B; w_B; qd]), whose velocity ripple has zero mean over the
period and, at the sample instants,

    u_r = -(dt / 12) H^-1 [0; K_p (T_k - T_k-1)]

(the integral of a (1/2 - s/dt) less its mean, at s = 0), while the joint angles' ripple is zero
there (to O(dt^3)). So the encoders' samples, and every rate derived from them, describe the
smooth motion, but the accelerometer's period mean, the change of the IMU point's velocity between
two sample instants, holds (v_r(t_k) - v_r(t_k-1)) / dt with v_r = J_I u_r: zero at a steady
target rate, a step of the momentum where the rate changes (the servos' turnarounds). No filter of
the readings removes it (it is O(dt^2): 0.18 % of the mass at 62.5 Hz under the fastest arm
motion, 0.05 % at 125 Hz); ``servo_ripple`` models it from the servo targets' rate, the servos'
gains (``RobotDescription.servo_gain``) and the cargo's current estimate, and the estimator takes
it off the reading (``per_step.EstimatorInputs``). The peers that hold the same cargo are left
out of H (their inertia would lower the ripple that a robot's own servos give its IMU), and so
is K_v's share of the sawtooth.

Units: P in N s and N m s, Q and the balance in N and N m, velocities m/s and rad/s.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from .geometry import (
    cross3_into,
    exp_so3_into,
    matmul3_into,
    matvec3_into,
    skew_into,
)
from .rne import (
    Balance,
    RobotArrays,
    RobotDescription,
    as_single,
    body_regressor_kernel,
    grasp_from_base_into,
)

# Layout of the momentum-form sample (``momentum_sample``'s vector), all in G.
THRUST = slice(0, 6)  # propulsion wrench, N and N m about G's origin
LINKS_P = slice(6, 12)  # links' momentum [p; L], N s and N m s
LINKS_Q = slice(12, 18)  # links' non-derivative part, N and N m
CARGO_P = slice(18, 24)  # [nu_G (m/s); w_G (rad/s)]: P_Y = CARGO_P_MAP [nu_G; w_G]
CARGO_Q = slice(24, 33)  # [c (m/s^2); w_G's 6 products (rad/s)^2]: Q_Y = CARGO_Q_MAP [...]
SIZE = 33
# The pairs (i, j) of w_i w_j in CARGO_Q, after c.
_PRODUCTS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _regressor_maps() -> tuple[np.ndarray, np.ndarray]:
    """(M_P (60, 6), M_Q (60, 9)): Y(nu, 0, w).ravel() = M_P [nu; w] and
    Y(c, w, 0).ravel() = M_Q [c; w_i w_j over ``_PRODUCTS``] (module docstring)."""
    zero, unit = np.zeros(3), np.eye(3)
    m_p = np.zeros((60, 6))
    m_q = np.zeros((60, 9))
    for i in range(3):
        m_p[:, i] = body_regressor_kernel(unit[i], zero, zero).ravel()
        m_p[:, 3 + i] = body_regressor_kernel(zero, zero, unit[i]).ravel()
        m_q[:, i] = m_p[:, i]
    square = [body_regressor_kernel(zero, unit[i], zero).ravel() for i in range(3)]
    for col, (i, j) in enumerate(_PRODUCTS):
        if i == j:
            m_q[:, 3 + col] = square[i]
        else:  # the quadratic form's cross term
            pair = body_regressor_kernel(zero, unit[i] + unit[j], zero).ravel()
            m_q[:, 3 + col] = pair - square[i] - square[j]
    return m_p, m_q


CARGO_P_MAP, CARGO_Q_MAP = _regressor_maps()


@njit(cache=True, inline="always")
def _link_frames_into(geo, arrays, q, vec, mat):
    """The link frames in B at joint angles ``q`` into ``geo``'s rot (n_links, 3, 3), pos
    (n_links, 3) m, grasp_rot and grasp_pos (``rne``'s first pass without the rates, in 3x3
    loops); ``vec`` (2, 3) and ``mat`` (2, 3, 3) are scratch."""
    rot, pos = geo.rot, geo.pos
    for i in range(3):
        for j in range(3):
            rot[0, i, j] = 1.0 if i == j else 0.0
        pos[0, i] = 0.0
    rotvec, offset, joint, to_joint = vec[0], vec[1], mat[0], mat[1]
    for k in range(1, arrays.parent.shape[0]):
        p = arrays.parent[k]
        for i in range(3):
            rotvec[i] = arrays.joint_axis[k, i] * q[k - 1]
        exp_so3_into(joint, rotvec)
        matmul3_into(to_joint, rot[p], arrays.rot_in_parent[k])
        matmul3_into(rot[k], to_joint, joint)
        matvec3_into(offset, rot[p], arrays.pos_in_parent[k])
        for i in range(3):
            pos[k, i] = pos[p, i] + offset[i]
    g = arrays.grasp_link
    matmul3_into(geo.grasp_rot, rot[g], arrays.grasp_rot)
    matvec3_into(offset, rot[g], arrays.grasp_pos)
    for i in range(3):
        geo.grasp_pos[i] = pos[g, i] + offset[i]


@njit(cache=True, inline="always")
def _mass_geometry_into(geo, arrays, turned):
    """The links' mass distribution in B at ``geo``'s link frames into its com_b (centres of
    mass relative to the link origins, m), inertia_b (about them, R_k I_k R_k^T, kg m^2) and
    first_moment (sum m_k rho_k about G's origin, kg m); returns the total mass kg. ``turned``
    (3, 3) is scratch."""
    rot, pos, com_b, inertia_b = geo.rot, geo.pos, geo.com_b, geo.inertia_b
    geo.first_moment[:] = 0.0
    total_mass = 0.0
    for k in range(arrays.parent.shape[0]):
        matvec3_into(com_b[k], rot[k], arrays.com[k])
        matmul3_into(turned, rot[k], arrays.inertia_com[k])
        matmul3_into(inertia_b[k], turned, rot[k].T)
        for i in range(3):
            geo.first_moment[i] += arrays.mass[k] * (pos[k, i] + com_b[k, i] - geo.grasp_pos[i])
        total_mass += arrays.mass[k]
    return total_mass


@njit(cache=True, inline="always")
def _link_rates_into(w, arrays, rot, w_base, qd, axis):
    """Angular velocities into ``w`` (n, n_links, 3) of the links in B at the link frames
    ``rot``, for n rows of base rates ``w_base`` (n, 3) and joint rates ``qd`` (n, nj):
    w_k = w_parent + qd_k R_k axis_k. ``axis`` (3,) is scratch."""
    w[:, 0] = w_base
    for k in range(1, arrays.parent.shape[0]):
        matvec3_into(axis, rot[k], arrays.joint_axis[k])
        p = arrays.parent[k]
        for r in range(w.shape[0]):
            for i in range(3):
                w[r, k, i] = w[r, p, i] + qd[r, k - 1] * axis[i]


@njit(cache=True, inline="always")
def _momentum_terms(arrays, imu_pos, geo, w, acc_imu, out, work):
    """Fill out[:, 6:SIZE] (n rows of P_links, Q_links, the cargo's P and Q arguments; module
    docstring) from the links' positions and mass distribution at the link geometry ``geo``,
    their angular velocities ``w`` (n, n_links, 3) and the IMU point's acceleration (n, 3), all
    in B; row by row (``_momentum_row``), with the levers between the links' points once, in
    ``work``'s (``MomentumWork``) levers, rho and vel."""
    n_links = arrays.parent.shape[0]
    pos, com_b, grasp_pos, g = geo.pos, geo.com_b, geo.grasp_pos, arrays.grasp_link
    # levers[0]: the base origin from the IMU point; levers[k]: link k's origin from its
    # parent's; levers[n_links]: G's origin from its link's.
    levers, rho = work.levers, work.rho  # rho: the links' centres of mass from G's origin
    for i in range(3):
        levers[0, i] = -imu_pos[i]
        levers[n_links, i] = grasp_pos[i] - pos[g, i]
        for k in range(n_links):
            if k > 0:
                levers[k, i] = pos[k, i] - pos[arrays.parent[k], i]
            rho[k, i] = pos[k, i] + com_b[k, i] - grasp_pos[i]
    for r in range(w.shape[0]):
        _momentum_row(arrays, geo, levers, rho, w[r], acc_imu[r], out[r], work.vel, work.vec)


@njit(cache=True, inline="always")
def _momentum_row(arrays, geo, levers, rho, w, acc_imu, out, vel, work):
    """One row of ``_momentum_terms``: the links' velocities relative to the frame translating
    with the IMU point, nu_k = nu_parent + w_parent x lever_k, their momentum
    p = sum m_k (nu_k + w_k x c_k) and angular momentum L = sum I_k w_k + m_k rho_k x nu_k about
    G's origin, then P and Q in G (module docstring). ``vel`` (n_links, 3) and ``work``
    (12, 3) are scratch."""
    t, u, nu, nu_g, momentum, ang = work[0], work[1], work[2], work[3], work[4], work[5]
    w_g, p_g, l_g, nu_gg, force, moment = work[6], work[7], work[8], work[9], work[10], work[11]
    g = arrays.grasp_link
    cross3_into(vel[0], w[0], levers[0])
    for k in range(1, vel.shape[0]):
        p = arrays.parent[k]
        cross3_into(t, w[p], levers[k])
        for i in range(3):
            vel[k, i] = vel[p, i] + t[i]
    cross3_into(t, w[g], levers[vel.shape[0]])
    for i in range(3):
        nu_g[i] = vel[g, i] + t[i]
    momentum[:], ang[:] = 0.0, 0.0
    for k in range(vel.shape[0]):
        cross3_into(t, w[k], geo.com_b[k])
        for i in range(3):
            nu[i] = vel[k, i] + t[i]
        m = arrays.mass[k]
        matvec3_into(t, geo.inertia_b[k], w[k])
        cross3_into(u, rho[k], nu)
        for i in range(3):
            momentum[i] += m * nu[i]
            ang[i] += t[i] + m * u[i]
    rot_t = geo.grasp_rot.T
    matvec3_into(w_g, rot_t, w[g])
    matvec3_into(p_g, rot_t, momentum)
    matvec3_into(l_g, rot_t, ang)
    out[6:9], out[9:12] = p_g, l_g
    for i in range(3):
        force[i] = geo.total_mass * acc_imu[i]
    matvec3_into(t, rot_t, force)
    cross3_into(u, w_g, p_g)
    for i in range(3):
        out[12 + i] = t[i] + u[i]
    cross3_into(t, geo.first_moment, acc_imu)
    cross3_into(u, nu_g, momentum)
    for i in range(3):
        moment[i] = t[i] + u[i]  # about G's origin, B axes
    matvec3_into(t, rot_t, moment)
    cross3_into(u, w_g, l_g)
    for i in range(3):
        out[15 + i] = t[i] + u[i]
    matvec3_into(nu_gg, rot_t, nu_g)
    out[18:21], out[21:24] = nu_gg, w_g
    matvec3_into(t, rot_t, acc_imu)
    cross3_into(u, w_g, nu_gg)
    for i in range(3):
        out[24 + i] = t[i] + u[i]
    for col in range(6):
        i, j = _PRODUCTS[col]
        out[27 + col] = w_g[i] * w_g[j]


class LinkGeometry(NamedTuple):
    """What a momentum-form sample needs of the joint angles alone (``link_geometry``), in B."""

    rot: np.ndarray  # (n_links, 3, 3) link rotations
    pos: np.ndarray  # (n_links, 3) link origins, m
    grasp_rot: np.ndarray  # (3, 3) G's rotation
    grasp_pos: np.ndarray  # (3,) G's origin, m
    grasp_from_base: np.ndarray  # (6, 6) wrench map B -> G (``rne.grasp_from_base_kernel``)
    com_b: np.ndarray  # (n_links, 3) centres of mass relative to the link origins, m
    inertia_b: np.ndarray  # (n_links, 3, 3) inertias about them, kg m^2
    total_mass: float  # kg
    first_moment: np.ndarray  # (3,) sum m_k rho_k about G's origin, kg m


class MomentumWork(NamedTuple):
    """Scratch of a momentum pass over n rows of motion (``momentum_work``), so that
    ``momentum_at_into`` and ``momentum_pass_into`` allocate nothing."""

    w_rows: np.ndarray  # (n, 3) base rates, rad/s
    acc_rows: np.ndarray  # (n, 3) the IMU point's accelerations, m/s^2
    qd_rows: np.ndarray  # (n, nj) joint rates, rad/s
    w: np.ndarray  # (n, n_links, 3) the links' angular velocities, rad/s
    rows: np.ndarray  # (n, SIZE) the samples
    levers: np.ndarray  # (n_links + 1, 3) m
    rho: np.ndarray  # (n_links, 3) m
    vel: np.ndarray  # (n_links, 3) m/s
    vec: np.ndarray  # (12, 3) 3-vectors
    mat: np.ndarray  # (2, 3, 3) 3x3 matrices


@njit(cache=True)
def momentum_work(n_links, n, nj):
    """A ``MomentumWork`` for n rows of a robot of n_links links and nj joints."""
    return MomentumWork(
        np.empty((n, 3)), np.empty((n, 3)), np.empty((n, nj)), np.empty((n, n_links, 3)),
        np.empty((n, SIZE)), np.empty((n_links + 1, 3)), np.empty((n_links, 3)),
        np.empty((n_links, 3)), np.empty((12, 3)), np.empty((2, 3, 3)),
    )  # fmt: skip


@njit(cache=True)
def geometry_work(n_links):
    """The arrays of a ``LinkGeometry`` of n_links links, for ``link_geometry_into``."""
    return LinkGeometry(
        np.empty((n_links, 3, 3)), np.empty((n_links, 3)), np.empty((3, 3)), np.empty(3),
        np.empty((6, 6)), np.empty((n_links, 3)), np.empty((n_links, 3, 3)), 0.0, np.empty(3),
    )  # fmt: skip


@njit(cache=True, inline="always")
def link_geometry_into(geo, arrays, q, vec, mat):
    """``link_geometry`` written into the arrays of ``geo`` (``geometry_work``), ``vec``
    (2, 3) and ``mat`` (2, 3, 3) as scratch: the same ``LinkGeometry``, its total mass set."""
    _link_frames_into(geo, arrays, q, vec, mat)
    total_mass = _mass_geometry_into(geo, arrays, mat[0])
    grasp_from_base_into(geo.grasp_from_base, geo.grasp_rot, geo.grasp_pos)
    return LinkGeometry(geo.rot, geo.pos, geo.grasp_rot, geo.grasp_pos, geo.grasp_from_base,
                        geo.com_b, geo.inertia_b, total_mass, geo.first_moment)  # fmt: skip


@njit(cache=True)
def link_geometry(arrays, q):
    """The link frames and mass distribution at joint angles ``q`` (``LinkGeometry``): the part
    of ``momentum_pass`` that the rates, the acceleration and the thrust leave unchanged."""
    geo = geometry_work(arrays.parent.shape[0])
    return link_geometry_into(geo, arrays, q, np.empty((2, 3)), np.empty((2, 3, 3)))


@njit(cache=True, inline="always")
def momentum_at_into(out, arrays, imu_pos, geo, w_base, acc_imu, qd, thrust_base, work):
    """``momentum_at`` into ``out`` (n, ``SIZE``), ``work`` (``MomentumWork`` of n rows or
    more) as scratch; the thrust's rows T_GB thrust_B in loops."""
    w = work.w[: w_base.shape[0]]
    _link_rates_into(w, arrays, geo.rot, w_base, qd, work.vec[0])
    for r in range(w_base.shape[0]):
        for i in range(6):
            total = 0.0
            for k in range(6):
                total += geo.grasp_from_base[i, k] * thrust_base[k]
            out[r, i] = total
    _momentum_terms(arrays, imu_pos, geo, w, acc_imu, out, work)


@njit(cache=True)
def momentum_at(arrays, imu_pos, geo, w_base, acc_imu, qd, thrust_base):
    """``momentum_pass`` without the rate noise's expectation at the link geometry ``geo``
    (``link_geometry`` of the joint angles), for n rows of motion at once (base rates
    ``w_base`` (n, 3), the IMU point's acceleration ``acc_imu`` (n, 3), joint rates ``qd``
    (n, nj)) and one thrust (6,): the samples (n, ``SIZE``)."""
    n = w_base.shape[0]
    out = np.empty((n, SIZE))
    work = momentum_work(arrays.parent.shape[0], n, qd.shape[1])
    momentum_at_into(out, arrays, imu_pos, geo, w_base, acc_imu, qd, thrust_base, work)
    return out


@njit(cache=True)
def momentum_pass(arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, qd_var):
    """One sample's momentum form in G (module docstring): the vector (``SIZE``,)
    [thrust_G, P_links, Q_links, cargo P arguments, cargo Q arguments], less the expectation of
    the joint-rate noise's square in Q (variances ``qd_var`` (nj,), ``momentum_sample``), and
    G's pose in B (rotation, origin)."""
    out, geo = momentum_pass_geometry(arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, qd_var)
    return out, geo.grasp_rot, geo.grasp_pos


@njit(cache=True)
def momentum_pass_geometry(arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, qd_var):
    """``momentum_pass``'s sample, with the link geometry of ``q`` (``link_geometry``) it
    used."""
    n_links, nj = arrays.parent.shape[0], q.shape[0]
    work = momentum_work(n_links, 1 + nj, nj)
    return momentum_pass_into(
        work, geometry_work(n_links), arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base, qd_var
    )


@njit(cache=True)
def momentum_pass_into(work, geo_work, arrays, imu_pos, w_base, acc_imu, q, qd, thrust_base,
                       qd_var):  # fmt: skip
    """``momentum_pass_geometry`` in the arrays of ``work`` (``MomentumWork`` of 1 + nj rows)
    and ``geo_work`` (``geometry_work``): the sample is a view of work.rows[0]."""
    nj = q.shape[0]
    geo = link_geometry_into(geo_work, arrays, q, work.vec, work.mat)
    # E[Q(n)] of zero-mean rate noise n: Q is quadratic in the rates (P linear), so it is
    # sum_j var_j Q(e_j), e_j = 1 rad/s on joint j alone, base at rest, no acceleration: the
    # rows 1 + j beside the sample's row 0.
    w_rows, acc_rows, qd_rows = work.w_rows, work.acc_rows, work.qd_rows
    w_rows[:], acc_rows[:], qd_rows[:] = 0.0, 0.0, 0.0
    w_rows[0], acc_rows[0], qd_rows[0] = w_base, acc_imu, qd
    for j in range(nj):
        qd_rows[1 + j, j] = 1.0
    rows = work.rows
    momentum_at_into(rows, arrays, imu_pos, geo, w_rows, acc_rows, qd_rows, thrust_base, work)
    out = rows[0]
    for j in range(nj):
        if qd_var[j] > 0.0:
            for c in range(LINKS_Q.start, LINKS_Q.stop):
                out[c] -= qd_var[j] * rows[1 + j, c]
            for c in range(CARGO_Q.start, CARGO_Q.stop):
                out[c] -= qd_var[j] * rows[1 + j, c]
    return out, geo


@njit(cache=True)
def sample_geometry_from_rate_filter(arrays, imu_pos, rate_state, qd_var):
    """``momentum_pass_geometry`` of the rate filter's state (3, 12 + nj) over [gyro_B; the IMU
    point's acceleration in B; q; thrust_B] (``preprocess.Preprocessor``): its values, and the
    joint rates from its first derivative. Returns the sample and the link geometry it used."""
    nj = rate_state.shape[1] - 12
    y, yd = rate_state[0], rate_state[1]
    return momentum_pass_geometry(
        arrays, imu_pos, y[0:3], y[3:6], y[6 : 6 + nj], yd[6 : 6 + nj], y[6 + nj : 12 + nj], qd_var
    )


@njit(cache=True)
def _sample_from_rate_filter(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, imu_pos, rate_state, qd_var,
):  # fmt: skip
    """``sample_geometry_from_rate_filter``'s sample and G's pose in B (rotation, origin)."""
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    out, geo = sample_geometry_from_rate_filter(arrays, imu_pos, rate_state, qd_var)
    return out, geo.grasp_rot, geo.grasp_pos


def momentum_sample(
    robot: RobotDescription,
    w_base: np.ndarray,
    acc_imu: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    thrust_base: np.ndarray,
    qd_var: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One sample of the balance in momentum form (module docstring), G coordinates.

    ``w_base`` (3,) rad/s: the base's angular velocity in B; ``acc_imu`` (3,) m/s^2: the IMU
    point's acceleration in B; ``q``, ``qd`` (n_joints,) rad, rad/s; ``thrust_base`` (6,): the
    propulsion wrench in B about B's origin. ``qd_var`` (n_joints,) (rad/s)^2: the variance of
    the noise on ``qd``, whose square in Q's products of rates would bias it (its expectation
    is subtracted; None: no noise). Returns the vector (``SIZE``,) [thrust_G (6), P_links (6),
    Q_links (6), [nu_G; w_G] (6), [c; w_G's products] (9)] (slices ``THRUST`` ... ``CARGO_Q``)
    and G's pose in B (rotation (3, 3), origin (3,) m)."""
    nj = (robot.n_joints,)
    var = np.zeros(nj) if qd_var is None else qd_var
    args = [as_single(x, shape, name) for x, shape, name in (
        (w_base, (3,), "w_base"), (acc_imu, (3,), "acc_imu"), (q, nj, "q"), (qd, nj, "qd"),
        (thrust_base, (6,), "thrust_base"), (var, nj, "qd_var"),
    )]  # fmt: skip
    imu_pos = np.ascontiguousarray(robot.imu_pos, dtype=float)
    return momentum_pass(robot.arrays, imu_pos, *args)


def rate_square_terms(robot: RobotDescription, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The quadratic form of Q in the joint rates at joint angles ``q``, base at rest: for
    independent zero-mean rate noises n_j (variance v each), Q(n) - E Q(n) =
    sum_j (n_j^2 - v) A_jj + sum_i<j n_i n_j (A_ij + A_ji). Returns those vectors (``SIZE``,),
    Q(e_j) and Q(e_i + e_j) - Q(e_i) - Q(e_j) (P's slices zero), stacked (k, ``SIZE``), and each
    one's weight w (k,) in Var = w v^2 of white Gaussian noise (2 for a square, 1 for a product:
    the noise model's factor)."""
    nj = robot.n_joints
    q = as_single(q, (nj,), "q")
    imu_pos = np.ascontiguousarray(robot.imu_pos, dtype=float)
    terms = _rate_square_terms(*robot.arrays, imu_pos, q)
    weights = np.array([2.0] * nj + [1.0] * (len(terms) - nj))
    return terms, weights


@njit(cache=True)
def _rate_square_terms(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, imu_pos, q,
):  # fmt: skip
    """`rate_square_terms`' vectors: the squares' rows, then the pairs' (i < j)."""
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    nj = q.shape[0]
    n_terms = nj + nj * (nj - 1) // 2
    # Unit rates on each joint, then on each pair (i < j) of joints, base at rest.
    rates = np.zeros((n_terms, nj))
    rates[:nj] = np.eye(nj)
    row = nj
    for i in range(nj):
        for j in range(i + 1, nj):
            rates[row, i] = rates[row, j] = 1.0
            row += 1
    keep = np.zeros(SIZE)
    keep[LINKS_Q] = keep[CARGO_Q] = 1.0
    rest = np.zeros((n_terms, 3))
    samples = momentum_at(arrays, imu_pos, link_geometry(arrays, q), rest, rest, rates, np.zeros(6))
    terms = keep * samples
    row = nj
    for i in range(nj):
        for j in range(i + 1, nj):
            terms[row] = terms[row] - terms[i] - terms[j]
            row += 1
    return terms


def cargo_regressor_parts(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P_Y, Q_Y) (..., 6, 10) each of momentum-form vectors ``y`` (..., ``SIZE``) (or of
    their filtered values or derivatives: the maps are linear)."""
    lead = y.shape[:-1] + (6, 10)
    return (
        (y[..., CARGO_P] @ CARGO_P_MAP.T).reshape(lead),
        (y[..., CARGO_Q] @ CARGO_Q_MAP.T).reshape(lead),
    )


def balance_from_filtered(y: np.ndarray, yd: np.ndarray) -> Balance:
    """The filtered balance H[Z] = H'[P] + H[Q] from the balance filter's value ``y`` and
    derivative ``yd`` outputs (``SIZE``,) of momentum-form samples (compiled, new arrays)."""
    y, yd = np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(yd, dtype=float)
    return Balance(*_filtered_balance(y, yd, CARGO_P_MAP, CARGO_Q_MAP))


@njit(cache=True)
def _filtered_balance(y, yd, p_map, q_map):
    """(thrust, links = P_links' + Q_links, regressor = M_P P_Y' + M_Q Q_Y (6, 10))."""
    regressor = p_map @ yd[CARGO_P] + q_map @ y[CARGO_Q]
    return y[THRUST].copy(), yd[LINKS_P] + y[LINKS_Q], regressor.reshape(6, 10)


# ------------------------------------------------------------------ the servos' ripple
@njit(cache=True, inline="always")
def _body_jacobian_into(jac, arrays, rot, pos, link, point, axis):
    """The map ``jac`` (6, 6 + n_joints) from the generalised velocity u = [v_B (velocity of B's
    origin); w_B; qd] (B coordinates) to [velocity of ``point``; angular velocity] of a body rigid
    with link ``link`` (``point`` in B, m): [1, -[point]x, (axis_k x (point - pos_k))_k;
    0, 1, (axis_k)_k] over the joints k between the base and the link. ``axis`` (2, 3) scratch."""
    jac[:] = 0.0
    for i in range(3):
        jac[i, i] = jac[3 + i, 3 + i] = 1.0
    skew_into(jac[0:3, 3:6], point)  # w x point = -point x w
    for i in range(3):
        for j in range(3):
            jac[i, 3 + j] = -jac[i, 3 + j]
    k = link
    while k > 0:  # the joints between the base and the body
        matvec3_into(axis[0], rot[k], arrays.joint_axis[k])
        for i in range(3):
            axis[1, i] = point[i] - pos[k, i]
        cross3_into(jac[0:3, 5 + k], axis[0], axis[1])
        jac[3:6, 5 + k] = axis[0]
        k = arrays.parent[k]


@njit(cache=True, inline="always")
def _add_body_inertia(h, jac, mass, first_moment, inertia, spatial, moved):
    """h += J^T M J in loops, M = [[m 1, -[c]x], [[c]x, I_o]] (6, 6) the body's spatial inertia
    about a point o (first moment c about o, inertia I_o about o; its kinetic energy is
    1/2 [v_o; w]^T M [v_o; w]), J (6, n) its ``_body_jacobian_into`` at o; ``spatial`` (6, 6)
    and ``moved`` (6, n) scratch (M, then M J)."""
    spatial[:] = 0.0
    skew_into(spatial[3:6, 0:3], first_moment)
    for i in range(3):
        spatial[i, i] = mass
        for j in range(3):
            spatial[i, 3 + j] = -spatial[3 + i, j]
            spatial[3 + i, 3 + j] = inertia[i, j]
    n = jac.shape[1]
    for a in range(6):
        for c in range(n):
            total = 0.0
            for b in range(6):
                total += spatial[a, b] * jac[b, c]
            moved[a, c] = total
    for c in range(n):
        for d in range(n):
            total = 0.0
            for a in range(6):
                total += jac[a, c] * moved[a, d]
            h[c, d] += total


@njit(cache=True)
def generalised_inertia(arrays, q, cargo):
    """The free-floating mass matrix (6 + n_joints, 6 + n_joints) of the robot holding the cargo
    (standard parameters ``cargo`` (10,) in G about G's origin), for u = [v_B; w_B; qd] in B:
    H = sum_k J_k^T M_k J_k over the links (about their centres of mass) and the cargo (about
    G's origin, rigid with the grasp link), in loops (``_add_body_inertia``)."""
    geo = link_geometry(arrays, q)
    n = 5 + arrays.parent.shape[0]
    h, jac, moved = np.zeros((n, n)), np.empty((6, n)), np.empty((6, n))
    spatial, turned = np.empty((6, 6)), np.empty((3, 3))
    axis, point, first_moment = np.empty((2, 3)), np.empty(3), np.zeros(3)
    for k in range(arrays.parent.shape[0]):  # about its centre of mass: no first moment
        for i in range(3):
            point[i] = geo.pos[k, i] + geo.com_b[k, i]
        _body_jacobian_into(jac, arrays, geo.rot, geo.pos, k, point, axis)
        _add_body_inertia(h, jac, arrays.mass[k], first_moment, geo.inertia_b[k], spatial, moved)
    c = cargo
    inertia_g = np.array([[c[4], c[7], c[8]], [c[7], c[5], c[9]], [c[8], c[9], c[6]]])
    matmul3_into(turned, geo.grasp_rot, inertia_g)
    matmul3_into(inertia_g, turned, geo.grasp_rot.T)  # R I_G R^T
    matvec3_into(first_moment, geo.grasp_rot, c[1:4])
    _body_jacobian_into(jac, arrays, geo.rot, geo.pos, arrays.grasp_link, geo.grasp_pos, axis)
    _add_body_inertia(h, jac, c[0], first_moment, inertia_g, spatial, moved)
    return h


@njit(cache=True)
def servo_ripple_map(arrays, imu_pos, q, cargo, dt_s):
    """The map (3, n_joints) (m/s per N m) from the servos' torque step at a period's start,
    K_p (T_k - T_k-1), to the IMU point's velocity ripple at the sample instants, B coordinates
    (module docstring, Servo ripple): v_r = J_I u_r, u_r = -(dt / 12) H^-1 [0; torque step],
    H = ``generalised_inertia``, J_I u = v_B + w_B x imu_pos."""
    nj = q.shape[0]
    select = np.zeros((6 + nj, nj))  # S^T: the joint torques' place in the generalised force
    for j in range(nj):
        select[6 + j, j] = 1.0
    ripple = np.linalg.solve(generalised_inertia(arrays, q, cargo), select)
    ripple *= -(dt_s / 12.0)
    out, turn = np.empty((3, nj)), np.empty(3)
    for j in range(nj):
        cross3_into(turn, ripple[3:6, j], imu_pos)
        for i in range(3):
            out[i, j] = ripple[i, j] + turn[i]
    return out


def servo_ripple_velocities(
    robot: RobotDescription, q: np.ndarray, cargo: np.ndarray, dt_s: float
) -> np.ndarray | None:
    """``servo_ripple_map`` (3, n_joints) m/s per N m of a robot at joint angles ``q`` rad
    holding ``cargo`` (10,) (G, about G's origin), scaled by its servos' gains: the IMU point's
    velocity ripple per rad/s of each servo target's rate over the period (its step at the
    period's start: T_k - T_k-1 = rate dt). None when the robot's ``servo_gain`` is unknown."""
    if robot.servo_gain is None:
        return None
    nj = (robot.n_joints,)
    q, cargo = as_single(q, nj, "q"), as_single(cargo, (10,), "cargo")
    imu_pos = np.ascontiguousarray(robot.imu_pos, dtype=float)
    gain = np.asarray(robot.servo_gain, dtype=float)
    dt_s = float(dt_s)
    return servo_ripple_map(robot.arrays, imu_pos, q, cargo, dt_s) * (gain * dt_s)


def servo_ripple(
    robot: RobotDescription,
    q: np.ndarray,
    cargo: np.ndarray,
    target_rate: np.ndarray,
    dt_s: float,
) -> np.ndarray:
    """The IMU point's servo ripple (3,) m/s, B coordinates, at the end of a period over which the
    robot's servo targets moved at ``target_rate`` (n_joints,) rad/s (``servo_ripple_velocities``
    times the rate). Zero when the robot's ``servo_gain`` is unknown."""
    per_rate = servo_ripple_velocities(robot, q, cargo, dt_s)
    if per_rate is None:
        return np.zeros(3)
    return per_rate @ as_single(target_rate, (robot.n_joints,), "target_rate")
