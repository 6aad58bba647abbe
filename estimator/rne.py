"""Sub-body Newton-Euler model of one free-flyer with a revolute arm holding the cargo.

Convention (used everywhere in this module): every vector is expressed in the robot's base
frame B (body-fixed, +x forward, +z deck for Astrobee), while every rate is an *inertial* rate.
So ``w`` is the inertial angular velocity written in B coordinates, ``a`` the inertial linear
acceleration of a point written in B coordinates, and so on. Moments are taken about the origin
of B unless a name says otherwise. A wrench is the 6-vector [force (N); moment (N m)]. Leading
array dimensions are batch dimensions (time samples); link arrays have the link index before the
last axis. Units: m, s, rad, kg.

Kinematics (seed paper eq. 1-4). Link k has parent p = parent[k], a fixed pose (R_pk0, p_pk) of
its frame in the parent frame at q_k = 0, and a revolute joint at its frame origin with unit axis
e_k in its own frame. With z_k = R_k e_k (axis in B):
    R_k   = R_p R_pk0 Rot(e_k, q_k)            p_k = p_p + R_p p_pk
    w_k   = w_p + qd_k z_k                     wd_k = wd_p + qdd_k z_k + w_p x (qd_k z_k)
    a_k   = a_p + wd_p x r + w_p x (w_p x r),  r = p_k - p_p        (acceleration of origin k)
    rdd_k = a_k + wd_k x c_k + w_k x (w_k x c_k),  c_k = R_k com_k  (centre of mass, eq. 1)
The cargo frame G is rigid with the grasp link (eq. 2-4): its origin acceleration follows from
the grasp link's as a_k does from a_p, and it shares the grasp link's w and wd.

Dynamics (seed eq. 5-6, several robots). The subsystem of robot i (its links and the cargo) is
acted on by its propulsion wrench and the wrenches the other robots apply to the cargo; joint
torques and the grasp force are internal and cancel. For any point o (here B's origin):
    W_thrust + sum_j W_j->cargo
        = sum_k [m_k rdd_k ; I_k wd_k + w_k x I_k w_k + (p_k + c_k) x m_k rdd_k]
          + T_BG Y(a_G, w_G, wd_G) pi
with Y the 6x10 body regressor of the cargo in its frame G (see ``body_regressor``), pi its standard
parameters in G, and T_BG the wrench transform from G to B. The balance is linear in pi, which
gives the UKF measurement, batch least squares and the Fisher information alike. The wrench robot
i applies to the cargo is what its propulsion delivers minus what its own links absorb:
    W_i->cargo = W_thrust - sum_k (link momentum rates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .inertia import skew


@dataclass(frozen=True)
class LinkDescription:
    """One rigid sub-body. ``joint_axis`` is None for the base (link 0)."""

    name: str
    parent: int
    joint_axis: np.ndarray | None
    rot_in_parent: np.ndarray  # (3, 3) frame at q = 0, in the parent frame
    pos_in_parent: np.ndarray  # (3,) origin (= joint position), in the parent frame
    mass: float
    com: np.ndarray  # (3,) in the link frame
    inertia_com: np.ndarray  # (3, 3) about the centre of mass, link frame axes


@dataclass(frozen=True)
class RobotDescription:
    """A robot's known model: links (base first, parents before children) and sensor frames.

    Frames of the IMU and the thrust site are given in the base frame, the grasp frame in the
    frame of link ``grasp_link``. ``joint_range`` (n_joints, 2) rad and ``thrust_limit`` (6,)
    N / N m are carried along for controllers.
    """

    links: tuple[LinkDescription, ...]
    imu_rot: np.ndarray
    imu_pos: np.ndarray
    thrust_rot: np.ndarray
    thrust_pos: np.ndarray
    grasp_link: int
    grasp_rot: np.ndarray
    grasp_pos: np.ndarray
    joint_range: np.ndarray
    thrust_limit: np.ndarray

    @property
    def n_joints(self) -> int:
        return len(self.links) - 1

    @property
    def total_mass(self) -> float:
        return float(sum(link.mass for link in self.links))


@dataclass(frozen=True)
class Kinematics:
    """Link and grasp-frame kinematics in base coordinates (leading batch dims ``...``)."""

    rot: np.ndarray  # (..., L, 3, 3) link frame in B
    pos: np.ndarray  # (..., L, 3) link origin in B
    w: np.ndarray  # (..., L, 3)
    wd: np.ndarray  # (..., L, 3)
    acc: np.ndarray  # (..., L, 3) acceleration of the link origin
    grasp_rot: np.ndarray  # (..., 3, 3) grasp frame G in B
    grasp_pos: np.ndarray  # (..., 3)
    grasp_acc: np.ndarray  # (..., 3) acceleration of G's origin
    grasp_w: np.ndarray  # (..., 3) angular velocity of G (that of the grasp link)
    grasp_wd: np.ndarray  # (..., 3)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis of two arrays (..., 3): np.cross, written out (np.cross costs
    ~10 us on small arrays; this is the same product, on Python floats for two 3-vectors)."""
    if a.ndim == 1 and b.ndim == 1:
        a0, a1, a2 = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))
    return np.stack(
        (
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ),
        axis=-1,
    )


def norm3(v: np.ndarray | tuple[float, float, float]) -> float:
    """|v| of one 3-vector (array or floats): np.linalg.norm's value (the same sum of squares),
    on floats."""
    x, y, z = v.tolist() if isinstance(v, np.ndarray) else v
    return math.sqrt(x * x + y * y + z * z)


def _axis_rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues rotation about a fixed unit ``axis`` (3,) by ``angle`` (...,) -> (..., 3, 3)."""
    k = skew(axis)
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def _rmv(rot: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", rot, v)


def propagate(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
) -> Kinematics:
    """Propagate base motion and joint motion out to every link and the grasp frame.

    ``w_base``, ``wd_base``: base angular velocity (rad/s) and acceleration (rad/s^2) in B;
    ``acc_base``: acceleration of B's origin (m/s^2) in B; ``q, qd, qdd``: (..., n_joints).
    """
    w_base = np.asarray(w_base, dtype=float)
    batch = w_base.shape[:-1]
    q, qd, qdd = (np.asarray(x, dtype=float) for x in (q, qd, qdd))
    nj = robot.n_joints
    for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
        if x.shape != (*batch, nj):
            raise ValueError(f"{name} must have shape {(*batch, nj)}, got {x.shape}")
    for name, x in (("wd_base", wd_base), ("acc_base", acc_base)):
        if np.shape(x) != (*batch, 3):
            raise ValueError(f"{name} must have shape {(*batch, 3)}, got {np.shape(x)}")
    rots = [np.broadcast_to(np.eye(3), (*batch, 3, 3))]
    poss = [np.zeros((*batch, 3))]
    ws = [w_base]
    wds = [np.asarray(wd_base, dtype=float)]
    accs = [np.asarray(acc_base, dtype=float)]
    for k, link in enumerate(robot.links[1:], start=1):
        p = link.parent
        jk = k - 1
        rot = rots[p] @ link.rot_in_parent @ _axis_rotation(link.joint_axis, q[..., jk])
        r = _rmv(rots[p], link.pos_in_parent)
        z = _rmv(rot, link.joint_axis)
        w_rel = qd[..., jk, None] * z
        rots.append(rot)
        poss.append(poss[p] + r)
        ws.append(ws[p] + w_rel)
        wds.append(wds[p] + qdd[..., jk, None] * z + cross(ws[p], w_rel))
        accs.append(accs[p] + cross(wds[p], r) + cross(ws[p], cross(ws[p], r)))
    g = robot.grasp_link
    r_g = _rmv(rots[g], robot.grasp_pos)
    grasp_acc = accs[g] + cross(wds[g], r_g) + cross(ws[g], cross(ws[g], r_g))
    return Kinematics(
        rot=np.stack(rots, axis=-3),
        pos=np.stack(poss, axis=-2),
        w=np.stack(ws, axis=-2),
        wd=np.stack(wds, axis=-2),
        acc=np.stack(accs, axis=-2),
        grasp_rot=rots[g] @ robot.grasp_rot,
        grasp_pos=poss[g] + r_g,
        grasp_acc=grasp_acc,
        grasp_w=ws[g],
        grasp_wd=wds[g],
    )


def link_poses(robot: RobotDescription, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every link frame in the base frame at joint angles ``q``: rotations (L, 3, 3) and
    origins (L, 3). The forward-kinematics part of ``propagate`` alone, ~10x cheaper."""
    rots, poss = [np.eye(3)], [np.zeros(3)]
    for k, link in enumerate(robot.links[1:]):
        rot_p = rots[link.parent]
        rots.append(rot_p @ link.rot_in_parent @ _axis_rotation(link.joint_axis, np.asarray(q[k])))
        poss.append(poss[link.parent] + rot_p @ link.pos_in_parent)
    return np.stack(rots), np.stack(poss)


def grasp_pose(robot: RobotDescription, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grasp frame in the base frame at joint angles ``q`` (rotation, position). Single sample,
    on Python floats (called per robot per step by the env and the controller); the same forward
    kinematics as ``link_poses`` and ``propagate`` (tests hold them equal)."""
    rot, pos = grasp_pose_rows(robot, np.asarray(q, dtype=float).tolist())
    return np.array(rot), np.array(pos)


def grasp_pose_rows(robot: RobotDescription, qs: list[float]) -> tuple[tuple, tuple]:
    """``grasp_pose`` as tuples of floats (3x3 rows, 3-vector) for the float helpers below."""
    _, g, grot, gpos, joints = _fast_constants(robot)
    rots = [((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))]
    poss = [(0.0, 0.0, 0.0)]
    for k, (parent, r0, pos, kk) in enumerate(joints):
        rot_0, r = _joint_frame(rots, parent, r0, pos)
        rots.append(m_m(rot_0, _rodrigues(kk, qs[k])))
        poss.append(v_add(poss[parent], r))
    rot_g = rots[g]
    return m_m(rot_g, grot), v_add(poss[g], m_v(rot_g, gpos))


def link_momentum_rate(robot: RobotDescription, kin: Kinematics) -> np.ndarray:
    """Sum over the robot's own links of the rate of change of momentum, as a wrench in B about
    B's origin (..., 6): what the robot's own bodies absorb of the external wrench."""
    mass = np.array([link.mass for link in robot.links])
    com_local = np.stack([link.com for link in robot.links])
    inertia_local = np.stack([link.inertia_com for link in robot.links])
    c = np.einsum("...kij,kj->...ki", kin.rot, com_local)
    inertia = kin.rot @ inertia_local @ np.swapaxes(kin.rot, -1, -2)
    rdd = kin.acc + cross(kin.wd, c) + cross(kin.w, cross(kin.w, c))
    f = mass[:, None] * rdd
    n = _rmv(inertia, kin.wd) + cross(kin.w, _rmv(inertia, kin.w)) + cross(kin.pos + c, f)
    return np.concatenate((f.sum(axis=-2), n.sum(axis=-2)), axis=-1)


def body_regressor(acc: np.ndarray, w: np.ndarray, wd: np.ndarray) -> np.ndarray:
    """Regressor Y (..., 6, 10) of one rigid body in its own frame: [f; n_o] = Y pi.

    ``acc`` is the acceleration of the frame origin o, ``w``/``wd`` the angular velocity and
    acceleration, all in the body frame; pi = [m, h, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] with
    h = m c and I about o. f = m a + wd x h + w x (w x h); n_o = I wd + w x (I w) + h x a.
    """
    acc, w, wd = (np.asarray(x, dtype=float) for x in (acc, w, wd))
    batch = np.broadcast_shapes(acc.shape, w.shape, wd.shape)[:-1]
    y = np.zeros((*batch, 6, 10))
    sw = skew(w)
    y[..., :3, 0] = acc
    y[..., :3, 1:4] = skew(wd) + sw @ sw
    y[..., 3:, 1:4] = -skew(acc)

    def lmat(v: np.ndarray) -> np.ndarray:
        # I v = L(v) [I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]
        out = np.zeros((*v.shape[:-1], 3, 6))
        x, yv, z = v[..., 0], v[..., 1], v[..., 2]
        out[..., 0, 0], out[..., 0, 3], out[..., 0, 4] = x, yv, z
        out[..., 1, 1], out[..., 1, 3], out[..., 1, 5] = yv, x, z
        out[..., 2, 2], out[..., 2, 4], out[..., 2, 5] = z, x, yv
        return out

    y[..., 3:, 4:] = lmat(wd) + sw @ lmat(w)
    return y


def wrench_transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """6x6 map (..., 6, 6) of a wrench [f; n about A's origin] in frame A to frame B, where A's
    pose in B is (rot, pos): f_B = R f, n_B = R n + pos x (R f)."""
    rot = np.asarray(rot, dtype=float)
    t = np.zeros((*rot.shape[:-2], 6, 6))
    t[..., :3, :3] = rot
    t[..., 3:, 3:] = rot
    t[..., 3:, :3] = skew(pos) @ rot
    return t


def grasp_from_base(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Inverse of ``wrench_transform(rot, pos)``: wrench in B (about B's origin) -> frame G whose
    pose in B is (rot, pos), moments about G's origin: f_G = R^T f, n_G = R^T (n - pos x f)."""
    rot_t = np.asarray(rot, dtype=float).T
    px, py, pz = np.asarray(pos, dtype=float).tolist()
    t = np.zeros((6, 6))
    t[:3, :3] = rot_t
    t[3:, 3:] = rot_t
    t[3:, :3] = -rot_t @ np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]])
    return t


def cargo_regressor(kin: Kinematics) -> np.ndarray:
    """A (..., 6, 10): the cargo's momentum rate as a wrench in B about B's origin is A pi, with
    pi the cargo's standard parameters in the grasp frame G."""
    rot_t = np.swapaxes(kin.grasp_rot, -1, -2)
    y = body_regressor(
        _rmv(rot_t, kin.grasp_acc), _rmv(rot_t, kin.grasp_w), _rmv(rot_t, kin.grasp_wd)
    )
    return wrench_transform(kin.grasp_rot, kin.grasp_pos) @ y


def thrust_wrench(robot: RobotDescription, command: np.ndarray) -> np.ndarray:
    """Propulsion wrench (..., 6) in B about B's origin from the thrust-site command
    [f (N); tau (N m)] in the thrust-site frame."""
    t = wrench_transform(robot.thrust_rot, robot.thrust_pos)
    return np.einsum("ij,...j->...i", t, command)


# ---------------------------------------------------------------------------------------------
# Fast path for one sample. The estimator evaluates the balance of one instant tens of times per
# second per robot; numpy's per-call overhead on 3-vectors made that 240 us. The same equations
# as ``propagate`` / ``link_momentum_rate`` / ``body_regressor`` written on Python floats; tests
# hold it equal to them to 1e-12. The helpers work on 3-vectors and 3x3 matrices (rows) as tuples
# of floats (as_rows makes them from arrays): m_v(m, v) = m v, mt_v(m, v) = m^T v, m_m(a, b) =
# a b, mt_m(a, b) = a^T b, m_mt(a, b) = a b^T. They also serve the env's navigation and
# observations, the estimator's attitude and the trajectories. Their products round as written
# (left to right, no fused multiply-add), unlike numpy's BLAS products of the same matrices.
def as_rows(mat) -> tuple:
    """A 3x3 matrix (array or nested sequences) as a tuple of row tuples of floats."""
    return tuple(map(tuple, np.asarray(mat, dtype=float).tolist()))


def v_add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def v_sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def v_scale(s, a):
    return (s * a[0], s * a[1], s * a[2])


def v_cross(a, b):
    a0, a1, a2 = a
    b0, b1, b2 = b
    return (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)


def point_acc(acc, w, wd, r):
    """acc + wd x r + w x (w x r): the acceleration of the point r of a rigid body whose origin
    accelerates at acc (the sums and products of v_add and v_cross, in one call)."""
    r0, r1, r2 = r
    w0, w1, w2 = w
    d0, d1, d2 = wd
    c0, c1, c2 = w1 * r2 - w2 * r1, w2 * r0 - w0 * r2, w0 * r1 - w1 * r0  # w x r
    return (
        acc[0] + (d1 * r2 - d2 * r1) + (w1 * c2 - w2 * c1),
        acc[1] + (d2 * r0 - d0 * r2) + (w2 * c0 - w0 * c2),
        acc[2] + (d0 * r1 - d1 * r0) + (w0 * c1 - w1 * c0),
    )


def m_v(m, v):
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m
    v0, v1, v2 = v
    return (
        m00 * v0 + m01 * v1 + m02 * v2,
        m10 * v0 + m11 * v1 + m12 * v2,
        m20 * v0 + m21 * v1 + m22 * v2,
    )


def mt_v(m, v):
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m
    v0, v1, v2 = v
    return (
        m00 * v0 + m10 * v1 + m20 * v2,
        m01 * v0 + m11 * v1 + m21 * v2,
        m02 * v0 + m12 * v1 + m22 * v2,
    )


def _euler_moment(inertia, w, wd):
    """I wd + w x (I w): a rigid body's rate of angular momentum about its centre of mass, all
    in one frame (v_add, m_v and v_cross in one call)."""
    (i00, i01, i02), (i10, i11, i12), (i20, i21, i22) = inertia
    w0, w1, w2 = w
    d0, d1, d2 = wd
    h0 = i00 * w0 + i01 * w1 + i02 * w2
    h1 = i10 * w0 + i11 * w1 + i12 * w2
    h2 = i20 * w0 + i21 * w1 + i22 * w2
    return (
        (i00 * d0 + i01 * d1 + i02 * d2) + (w1 * h2 - w2 * h1),
        (i10 * d0 + i11 * d1 + i12 * d2) + (w2 * h0 - w0 * h2),
        (i20 * d0 + i21 * d1 + i22 * d2) + (w0 * h1 - w1 * h0),
    )


def m_m(a, b):
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b
    return (
        (
            a00 * b00 + a01 * b10 + a02 * b20,
            a00 * b01 + a01 * b11 + a02 * b21,
            a00 * b02 + a01 * b12 + a02 * b22,
        ),
        (
            a10 * b00 + a11 * b10 + a12 * b20,
            a10 * b01 + a11 * b11 + a12 * b21,
            a10 * b02 + a11 * b12 + a12 * b22,
        ),
        (
            a20 * b00 + a21 * b10 + a22 * b20,
            a20 * b01 + a21 * b11 + a22 * b21,
            a20 * b02 + a21 * b12 + a22 * b22,
        ),
    )


def mt_m(a, b):
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b
    return (
        (
            a00 * b00 + a10 * b10 + a20 * b20,
            a00 * b01 + a10 * b11 + a20 * b21,
            a00 * b02 + a10 * b12 + a20 * b22,
        ),
        (
            a01 * b00 + a11 * b10 + a21 * b20,
            a01 * b01 + a11 * b11 + a21 * b21,
            a01 * b02 + a11 * b12 + a21 * b22,
        ),
        (
            a02 * b00 + a12 * b10 + a22 * b20,
            a02 * b01 + a12 * b11 + a22 * b21,
            a02 * b02 + a12 * b12 + a22 * b22,
        ),
    )


def m_mt(a, b):
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b
    return (
        (
            a00 * b00 + a01 * b01 + a02 * b02,
            a00 * b10 + a01 * b11 + a02 * b12,
            a00 * b20 + a01 * b21 + a02 * b22,
        ),
        (
            a10 * b00 + a11 * b01 + a12 * b02,
            a10 * b10 + a11 * b11 + a12 * b12,
            a10 * b20 + a11 * b21 + a12 * b22,
        ),
        (
            a20 * b00 + a21 * b01 + a22 * b02,
            a20 * b10 + a21 * b11 + a22 * b12,
            a20 * b20 + a21 * b21 + a22 * b22,
        ),
    )


def _rodrigues(kk, angle: float):
    """I + sin K + (1 - cos) K^2 for a precomputed (K, K^2)."""
    s, c1 = math.sin(angle), 1.0 - math.cos(angle)
    (k00, k01, k02), (k10, k11, k12), (k20, k21, k22) = kk[0]
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = kk[1]
    return (
        (1.0 + s * k00 + c1 * m00, s * k01 + c1 * m01, s * k02 + c1 * m02),
        (s * k10 + c1 * m10, 1.0 + s * k11 + c1 * m11, s * k12 + c1 * m12),
        (s * k20 + c1 * m20, s * k21 + c1 * m21, 1.0 + s * k22 + c1 * m22),
    )


def _joint_frame(rots, parent, rot_in_parent, pos_in_parent):
    """A link's frame at q = 0 and its origin relative to its parent's, in B axes: R_p R_pk0 and
    R_p p_pk (for a child of the base, R_p = I: the products are skipped, their values are the
    same)."""
    if parent == 0:
        return rot_in_parent, pos_in_parent
    rot_p = rots[parent]
    return m_m(rot_p, rot_in_parent), m_v(rot_p, pos_in_parent)


_FAST_CACHE: dict[int, tuple] = {}


def _fast_constants(robot: RobotDescription) -> tuple:
    key = id(robot)
    hit = _FAST_CACHE.get(key)
    if hit is not None and hit[0] is robot:
        return hit[1]
    links = []
    for link in robot.links:
        axis = None if link.joint_axis is None else tuple(float(x) for x in link.joint_axis)
        k = None
        if axis is not None:
            kx = skew(np.asarray(axis))
            k = (as_rows(kx), as_rows(kx @ kx))
        links.append(
            (
                link.parent,
                as_rows(link.rot_in_parent),
                tuple(float(x) for x in link.pos_in_parent),
                axis,
                k,
                float(link.mass),
                tuple(float(x) for x in link.com),
                as_rows(link.inertia_com),
            )
        )
    const = (
        tuple(links),
        robot.grasp_link,
        as_rows(robot.grasp_rot),
        tuple(float(x) for x in robot.grasp_pos),
        # The joints' links only, what forward kinematics needs: (parent, R_pk0, p_pk, (K, K^2)).
        tuple((parent, r0, pos, kk) for parent, r0, pos, _, kk, *_ in links[1:]),
    )
    _FAST_CACHE[key] = (robot, const)
    return const


def balance_in_grasp_frame(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    thrust_base: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One instant's wrench balance in the grasp frame G (moments about the grasp point):
    (thrust_G (6,), own links' momentum rate_G (6,), the cargo's body regressor Y (6, 10), and
    the grasp frame's rotation (3, 3) and position (3,) in B), so that
    thrust_G = links_G + Y pi_G - (peers' wrenches in G). Single sample; same equations as
    ``propagate``, ``link_momentum_rate`` and ``body_regressor``."""
    inputs = (w_base, wd_base, acc_base, q, qd, qdd, thrust_base)
    values, rot_g, p_g = balance_rows(robot, *(np.asarray(x, dtype=float).tolist() for x in inputs))
    return (
        np.array(values[0:6]),
        np.array(values[6:12]),
        np.array(values[12:72]).reshape(6, 10),
        np.array(rot_g),
        np.array(p_g),
    )


def balance_rows(robot: RobotDescription, w_base, wd_base, acc_base, q, qd, qdd, thrust_base):
    """``balance_in_grasp_frame`` on lists of floats: (thrust_G, links_G, Y row by row) as one
    tuple of 72 floats, the grasp frame's rotation (rows) and position (the estimator filters
    the 72 values as one vector)."""
    links, g, grot, gpos, _ = _fast_constants(robot)
    rots = [((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))]
    poss = [(0.0, 0.0, 0.0)]
    ws = [w_base]
    wds = [wd_base]
    accs = [acc_base]
    qs, qds, qdds = q, qd, qdd
    f_sum = (0.0, 0.0, 0.0)
    n_sum = (0.0, 0.0, 0.0)
    for k, (parent, r0, pos, axis, kk, mass, com, inertia) in enumerate(links):
        if k:
            j = k - 1
            rot_0, r = _joint_frame(rots, parent, r0, pos)
            rot = m_m(rot_0, _rodrigues(kk, qs[j]))
            z = m_v(rot, axis)
            w_rel = v_scale(qds[j], z)
            wp, wdp = ws[parent], wds[parent]
            rots.append(rot)
            poss.append(v_add(poss[parent], r))
            ws.append(v_add(wp, w_rel))
            wds.append(v_add(v_add(wdp, v_scale(qdds[j], z)), v_cross(wp, w_rel)))
            accs.append(point_acc(accs[parent], wp, wdp, r))
        rot, w, wd = rots[k], ws[k], wds[k]
        cvec = m_v(rot, com)
        f = v_scale(mass, point_acc(accs[k], w, wd, cvec))
        w_l, wd_l = mt_v(rot, w), mt_v(rot, wd)
        n_l = _euler_moment(inertia, w_l, wd_l)
        n = v_add(m_v(rot, n_l), v_cross(v_add(poss[k], cvec), f))
        f_sum = v_add(f_sum, f)
        n_sum = v_add(n_sum, n)
    # Grasp frame.
    rg = rots[g]
    r_g = m_v(rg, gpos)
    rot_g = m_m(rg, grot)
    p_g = v_add(poss[g], r_g)
    wg, wdg = ws[g], wds[g]
    acc_g = point_acc(accs[g], wg, wdg, r_g)

    def to_grasp(wrench):
        f3 = (wrench[0], wrench[1], wrench[2])
        n3 = (wrench[3], wrench[4], wrench[5])
        return mt_v(rot_g, f3) + mt_v(rot_g, v_sub(n3, v_cross(p_g, f3)))

    a, wv, wdv = mt_v(rot_g, acc_g), mt_v(rot_g, wg), mt_v(rot_g, wdg)
    values = to_grasp(thrust_base) + to_grasp(f_sum + n_sum) + _body_regressor_values(a, wv, wdv)
    return values, rot_g, p_g


def _body_regressor_values(a, w, wd) -> tuple:
    """``body_regressor`` for one sample on Python floats, its 60 values row by row: its matrix
    products written out, the terms that are products with zero dropped from their sums (the
    sums keep their order)."""
    a0, a1, a2 = a
    w0, w1, w2 = w
    d0, d1, d2 = wd
    # skew(w)^2: diagonal, then the symmetric off-diagonal entries.
    s00, s11, s22 = -(w1 * w1 + w2 * w2), -(w0 * w0 + w2 * w2), -(w0 * w0 + w1 * w1)
    s01, s02, s12 = w0 * w1, w0 * w2, w1 * w2
    # Columns [m, h (3), I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]; force rows: a, skew(wd) + skew(w)^2;
    # moment rows: -skew(a), L(wd) + skew(w) L(w) with I v = L(v) [I_xx .. I_yz].
    return (
        a0, s00, -d2 + s01, d1 + s02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        a1, d2 + s01, s11, -d0 + s12, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        a2, -d1 + s02, d0 + s12, s22, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        0.0, 0.0, a2, -a1,
        d0, (-w2) * w1, w1 * w2, d1 + (-w2) * w0, d2 + w1 * w0, (-w2) * w2 + w1 * w1,
        0.0, -a2, 0.0, a0,
        w2 * w0, d1, (-w0) * w2, d0 + w2 * w1, w2 * w2 + (-w0) * w0, d2 + (-w0) * w1,
        0.0, a1, -a0, 0.0,
        (-w1) * w0, w0 * w1, d2, (-w1) * w1 + w0 * w0, d0 + (-w1) * w2, d1 + w0 * w2,
    )  # fmt: skip
