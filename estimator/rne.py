"""Sub-body Newton-Euler model of one free-flyer with a revolute arm holding the cargo.

Frames and units. Every vector is expressed in the robot's base frame B (body-fixed, +x
forward, +z deck for Astrobee) while every rate is an *inertial* rate: ``w`` is the inertial
angular velocity written in B coordinates, ``acc`` the inertial linear acceleration of a point
written in B coordinates. Moments are about B's origin unless a name says otherwise. A wrench is
the 6-vector [force (N); moment (N m)]. Units: m, s, rad, kg. Rotation matrices map child
coordinates to parent coordinates (``estimator.geometry``). Link 0 is the base; link k > 0 has
parent ``parent[k] < k`` and the revolute joint k - 1 at its frame origin.

First pass, base -> links -> grasp -> cargo (seed paper eq. 1-4). Link k has a fixed pose
(R_pk0, p_pk) in its parent's frame at q = 0 and a unit joint axis e_k in its own frame. With
p = parent[k], j = k - 1 and z_k = R_k e_k the joint axis in B:

    R_k  = R_p R_pk0 exp(e_k q_j)                  p_k = p_p + r,  r = R_p p_pk
    w_k  = w_p + qd_j z_k                           wd_k = wd_p + qdd_j z_k + w_p x (qd_j z_k)
    a_k  = a_p + wd_p x r + w_p x (w_p x r)                    (origin of link k)

The last line is the acceleration of a point r of a rigid body whose origin accelerates at a:

    r_dd = a + wd x r + w x (w x r)                             (``point_acceleration``)

It gives each link's centre of mass (r = c_k = R_k com_k, eq. 1) and the grasp frame G, rigid
with link ``grasp_link`` (eq. 2-4; G shares that link's w and wd). The cargo is rigid with G.
The first line (the poses, the forward kinematics) is ``grasp_pose_into``, written once
and used by this pass and by the env's observations alike.

Second pass, links -> base: the rate of change of momentum of link k about B's origin,

    f_k = m_k rdd_k,    n_k = R_k (I_k wd_k' + w_k' x I_k w_k') + (p_k + c_k) x f_k,

with w_k' = R_k^T w_k, wd_k' = R_k^T wd_k in the link frame, where the inertia I_k about the
centre of mass is constant (Euler's equation), summed over the links (``link_momentum_rate``).
Joint torques are internal to the robot and cancel in the sum.

Balance (seed eq. 5-6, several robots). Robot i's subsystem (its links and the cargo) is acted
on by its propulsion wrench and the wrenches the other robots apply to the cargo:

    W_thrust + sum_j W_j->cargo = sum_k [f_k; n_k] + T_BG Y(a_G, w_G, wd_G) pi,

with pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] the cargo's standard parameters
in G (h = m c, I about G's origin), T_BG the wrench transform G -> B (``wrench_transform``) and Y
the 6x10 body regressor in G (``body_regressor``):

    f   = m a + wd x h + w x (w x h)      -> Y[:3] = [a, [wd]x + [w]x^2, 0]
    n_o = I wd + w x I w + h x a          -> Y[3:] = [0, -[a]x, L(wd) + [w]x L(w)],

where I v = L(v) [I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]. The balance is linear in pi, which gives
the UKF measurement, batch least squares and the Fisher information alike. The wrench robot i
applies to the cargo is what its propulsion delivers minus what its own links absorb:
W_i->cargo = W_thrust - sum_k [f_k; n_k].

Every computation is written once, for one sample, compiled with numba; the public functions
accept leading batch dimensions (time samples) and loop over them in compiled code.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
from numba import njit

from .geometry import cross3_into, exp_so3_into, matmul3_into, matvec3_into, skew


@dataclass(frozen=True)
class LinkDescription:
    """One rigid sub-body. ``joint_axis`` is None for the base (link 0)."""

    name: str
    parent: int
    joint_axis: np.ndarray | None
    rot_in_parent: np.ndarray  # (3, 3) frame at q = 0, in the parent frame
    pos_in_parent: np.ndarray  # (3,) origin (= joint position) m, in the parent frame
    mass: float  # kg
    com: np.ndarray  # (3,) m, in the link frame
    inertia_com: np.ndarray  # (3, 3) kg m^2 about the centre of mass, link frame axes


class RobotArrays(NamedTuple):
    """A robot's constants as contiguous float64 arrays, link index first (what the compiled
    kernels read by name). The base's row of ``joint_axis`` is zero and its ``parent`` -1."""

    parent: np.ndarray  # (L,) int64
    joint_axis: np.ndarray  # (L, 3) unit axis in the link frame
    rot_in_parent: np.ndarray  # (L, 3, 3)
    pos_in_parent: np.ndarray  # (L, 3) m
    mass: np.ndarray  # (L,) kg
    com: np.ndarray  # (L, 3) m, link frame
    inertia_com: np.ndarray  # (L, 3, 3) kg m^2, link frame axes
    grasp_link: int
    grasp_rot: np.ndarray  # (3, 3) grasp frame G in the grasp link's frame
    grasp_pos: np.ndarray  # (3,) m


@dataclass(frozen=True)
class RobotDescription:
    """A robot's known model: links (base first, parents before children) and sensor frames.

    Frames of the IMU and the thrust site are given in the base frame, the grasp frame in the
    frame of link ``grasp_link``. ``joint_range`` (n_joints, 2) rad and ``thrust_limit`` (6,)
    N / N m are carried along for controllers. ``servo_gain`` (n_joints,) N m/rad: the position
    servos' proportional gain (None: unknown; ``momentum.servo_ripple_velocities`` needs it).
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
    servo_gain: np.ndarray | None = None

    @property
    def n_joints(self) -> int:
        return len(self.links) - 1

    @property
    def total_mass(self) -> float:
        return float(sum(link.mass for link in self.links))

    @cached_property
    def arrays(self) -> RobotArrays:
        """The links' constants packed once for the compiled kernels."""
        for k, link in enumerate(self.links[1:], start=1):
            if not 0 <= link.parent < k or link.joint_axis is None:
                raise ValueError(f"link {k} ({link.name}) needs a joint axis and a parent < {k}")

        def stack(values) -> np.ndarray:
            return np.ascontiguousarray(np.stack([np.asarray(v, dtype=float) for v in values]))

        return RobotArrays(
            parent=np.array([-1] + [link.parent for link in self.links[1:]], dtype=np.int64),
            joint_axis=stack([np.zeros(3)] + [link.joint_axis for link in self.links[1:]]),
            rot_in_parent=stack([link.rot_in_parent for link in self.links]),
            pos_in_parent=stack([link.pos_in_parent for link in self.links]),
            mass=np.array([link.mass for link in self.links], dtype=float),
            com=stack([link.com for link in self.links]),
            inertia_com=stack([link.inertia_com for link in self.links]),
            grasp_link=int(self.grasp_link),
            grasp_rot=np.ascontiguousarray(self.grasp_rot, dtype=float),
            grasp_pos=np.ascontiguousarray(self.grasp_pos, dtype=float),
        )

    @cached_property
    def thrust_to_base(self) -> np.ndarray:
        """Wrench transform (6, 6) from the thrust site's frame to B (about B's origin)."""
        return wrench_transform(self.thrust_rot, self.thrust_pos)


@dataclass(frozen=True)
class Kinematics:
    """Link and grasp-frame kinematics in base coordinates (leading batch dims ``...``)."""

    rot: np.ndarray  # (..., L, 3, 3) link frame in B
    pos: np.ndarray  # (..., L, 3) link origin in B, m
    w: np.ndarray  # (..., L, 3) rad/s
    wd: np.ndarray  # (..., L, 3) rad/s^2
    acc: np.ndarray  # (..., L, 3) acceleration of the link origin, m/s^2
    grasp_rot: np.ndarray  # (..., 3, 3) grasp frame G in B
    grasp_pos: np.ndarray  # (..., 3) m
    grasp_acc: np.ndarray  # (..., 3) acceleration of G's origin, m/s^2
    grasp_w: np.ndarray  # (..., 3) angular velocity of G (that of the grasp link)
    grasp_wd: np.ndarray  # (..., 3)


@dataclass(frozen=True)
class Balance:
    """One instant's wrench balance in the grasp frame G (moments about G's origin, N and N m):
    ``thrust = links + regressor @ pi - sum_j T_G<-Gj W_j``, pi the cargo's parameters in G."""

    thrust: np.ndarray  # (6,) propulsion wrench
    links: np.ndarray  # (6,) rate of change of momentum of the robot's own links
    regressor: np.ndarray  # (6, 10) the cargo's body regressor Y in G

    SIZE = 72  # entries of ``to_vector``

    def to_vector(self) -> np.ndarray:
        """[thrust (6), links (6), regressor row by row (60)]: the quantities filtered together."""
        return np.concatenate((self.thrust, self.links, self.regressor.ravel()))

    @classmethod
    def from_vector(cls, values: np.ndarray) -> Balance:
        """Inverse of ``to_vector`` (views into ``values``)."""
        values = np.asarray(values, dtype=float)
        if values.shape != (cls.SIZE,):
            raise ValueError(f"a balance vector has shape ({cls.SIZE},), got {values.shape}")
        return cls(values[0:6], values[6:12], values[12:72].reshape(6, 10))


# ------------------------------------------------------------------------ compiled kernels
@njit(cache=True)
def point_acceleration(acc: np.ndarray, w: np.ndarray, wd: np.ndarray, r: np.ndarray) -> np.ndarray:
    """r_dd = acc + wd x r + w x (w x r) (3,): acceleration of the point r of a rigid body whose
    origin accelerates at ``acc``, all in one frame."""
    return acc + np.cross(wd, r) + np.cross(w, np.cross(w, r))


@njit(cache=True, inline="always")
def grasp_pose_into(rot_out, pos_out, rot, pos, lever, parent, joint_axis, rot_in_parent,
                    pos_in_parent, grasp_link, grasp_rot, grasp_pos, q):  # fmt: skip
    """Forward kinematics at joint angles q (n_joints,) rad, the positions of the first pass:

        R_k = R_p R_pk0 exp(e_k q_j),   r_k = R_p p_pk,   p_k = p_p + r_k    (links k >= 1)
        R_G = R_g R_gG,                 r_G = R_g p_gG,   p_G = p_g + r_G    (g = grasp_link)

    into ``rot`` (L + 1, 3, 3) (R_k; the last a scratch), ``pos`` (L, 3) (p_k, m), ``lever``
    (L + 1, 3) (r_k, m, r_0 = 0; the last r_G), ``rot_out`` (3, 3) R_G and ``pos_out`` (3,) p_G,
    all in B; the arguments between are ``RobotArrays``' fields. ``rot_out`` serves as scratch
    until the end. Allocates nothing: the env's observation kernels call it every step."""
    n_links = parent.shape[0]
    work = rot[n_links]
    rot[0], pos[0], lever[0] = 0.0, 0.0, 0.0  # the base: identity, at the origin
    for d in range(3):
        rot[0, d, d] = 1.0
    for k in range(1, n_links):
        p = parent[k]
        for d in range(3):  # the rotation vector e_k q_j, for now
            lever[k, d] = joint_axis[k, d] * q[k - 1]
        exp_so3_into(rot_out, lever[k])
        matmul3_into(work, rot[p], rot_in_parent[k])
        matmul3_into(rot[k], work, rot_out)
        matvec3_into(lever[k], rot[p], pos_in_parent[k])
        for d in range(3):
            pos[k, d] = pos[p, d] + lever[k, d]
    matvec3_into(lever[n_links], rot[grasp_link], grasp_pos)
    for d in range(3):
        pos_out[d] = pos[grasp_link, d] + lever[n_links, d]
    matmul3_into(rot_out, rot[grasp_link], grasp_rot)


@njit(cache=True)
def _forward_pass(arrays, w_base, wd_base, acc_base, q, qd, qdd):
    """First pass for one sample: the poses (``grasp_pose_into``), then the link frames' rates
    and origin accelerations, and the grasp frame's. Returns (rot, pos, w, wd, acc, grasp_rot,
    grasp_pos, grasp_acc) of ``Kinematics``."""
    n_links = arrays.parent.shape[0]
    rot, lever = np.empty((n_links + 1, 3, 3)), np.empty((n_links + 1, 3))
    pos, w, wd, acc = [np.empty((n_links, 3)) for _ in range(4)]
    grasp_rot, grasp_pos = np.empty((3, 3)), np.empty(3)
    grasp_pose_into(
        grasp_rot, grasp_pos, rot, pos, lever, arrays.parent, arrays.joint_axis,
        arrays.rot_in_parent, arrays.pos_in_parent, arrays.grasp_link, arrays.grasp_rot,
        arrays.grasp_pos, q,
    )  # fmt: skip
    w[0], wd[0], acc[0] = w_base, wd_base, acc_base
    for k in range(1, n_links):
        p, j = arrays.parent[k], k - 1
        z = rot[k] @ arrays.joint_axis[k]
        w_rel = qd[j] * z
        w[k] = w[p] + w_rel
        wd[k] = wd[p] + qdd[j] * z + np.cross(w[p], w_rel)
        acc[k] = point_acceleration(acc[p], w[p], wd[p], lever[k])
    g = arrays.grasp_link
    grasp_acc = point_acceleration(acc[g], w[g], wd[g], lever[n_links])
    return rot[:n_links], pos, w, wd, acc, grasp_rot, grasp_pos, grasp_acc


@njit(cache=True)
def _momentum_rate_pass(arrays, rot, pos, w, wd, acc) -> np.ndarray:
    """Second pass for one sample: sum over the links of [f_k; n_k] about B's origin (6,)."""
    out = np.zeros(6)
    for k in range(arrays.parent.shape[0]):
        c = rot[k] @ arrays.com[k]
        f = arrays.mass[k] * point_acceleration(acc[k], w[k], wd[k], c)
        inertia = arrays.inertia_com[k]
        w_link, wd_link = w[k] @ rot[k], wd[k] @ rot[k]  # R^T w, R^T wd
        euler = inertia @ wd_link + np.cross(w_link, inertia @ w_link)
        out[:3] += f
        out[3:] += rot[k] @ euler + np.cross(pos[k] + c, f)
    return out


@njit(cache=True)
def _inertia_map(v: np.ndarray) -> np.ndarray:
    """L(v) (3, 6) with I v = L(v) [I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]."""
    out = np.zeros((3, 6))
    out[0, 0], out[0, 3], out[0, 4] = v[0], v[1], v[2]
    out[1, 1], out[1, 3], out[1, 5] = v[1], v[0], v[2]
    out[2, 2], out[2, 4], out[2, 5] = v[2], v[0], v[1]
    return out


@njit(cache=True)
def body_regressor_kernel(acc: np.ndarray, w: np.ndarray, wd: np.ndarray) -> np.ndarray:
    """Y (6, 10) of one sample (acc, w, wd (3,) float64, body frame); ``body_regressor``'s
    equation, compiled and unchecked, for compiled callers."""
    y = np.zeros((6, 10))
    skew_w = skew(w)
    y[:3, 0] = acc
    y[:3, 1:4] = skew(wd) + skew_w @ skew_w
    y[3:, 1:4] = -skew(acc)
    y[3:, 4:] = _inertia_map(wd) + skew_w @ _inertia_map(w)
    return y


@njit(cache=True)
def _wrench_transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    t = np.zeros((6, 6))
    t[:3, :3] = rot
    t[3:, 3:] = rot
    t[3:, :3] = skew(pos) @ rot
    return t


@njit(cache=True, inline="always")
def grasp_from_base_into(out: np.ndarray, rot: np.ndarray, pos: np.ndarray) -> None:
    """``grasp_from_base`` (6, 6) into ``out``, in loops: f_G = R^T f, n_G = R^T (n - pos x f),
    whose lower-left block -R^T [pos]x has the rows pos x r_i (r_i the i-th column of R)."""
    out[:] = 0.0
    for i in range(3):
        for j in range(3):
            out[i, j] = rot[j, i]
            out[3 + i, 3 + j] = rot[j, i]
        cross3_into(out[3 + i, 0:3], pos, rot[:, i])


@njit(cache=True)
def grasp_from_base_kernel(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """``grasp_from_base`` (6, 6) compiled and unchecked, for compiled callers
    (``grasp_from_base_into``)."""
    out = np.empty((6, 6))
    grasp_from_base_into(out, rot, pos)
    return out


# Entry points called from Python take the fields of ``RobotArrays`` as separate arguments, in
# its order (numba types separate arrays far faster than a tuple of them), and assemble it.
@njit(cache=True)
def _grasp_pose(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, q,
):  # fmt: skip
    """G's pose in B at joint angles q (``grasp_pose_into`` into new arrays)."""
    n_links = parent.shape[0]
    rot, pos = np.empty((3, 3)), np.empty(3)
    grasp_pose_into(
        rot, pos, np.empty((n_links + 1, 3, 3)), np.empty((n_links, 3)),
        np.empty((n_links + 1, 3)), parent, joint_axis, rot_in_parent, pos_in_parent,
        grasp_link, grasp_rot, grasp_pos, q,
    )  # fmt: skip
    return rot, pos


@njit(cache=True)
def _grasp_balance(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, w_base, wd_base, acc_base, q, qd, qdd, thrust_base,
):  # fmt: skip
    """One sample's balance in G: (thrust_G, links_G, Y, grasp_rot, grasp_pos)."""
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    links_g, y, to_grasp, grasp_rot, grasp_pos = _links_and_regressor(
        arrays, w_base, wd_base, acc_base, q, qd, qdd
    )
    return to_grasp @ thrust_base, links_g, y, grasp_rot, grasp_pos


@njit(cache=True)
def _links_and_regressor(arrays, w_base, wd_base, acc_base, q, qd, qdd):
    """Both passes for one sample, in G: (links_G (6,), Y (6, 10), T_G<-B (6, 6), grasp_rot,
    grasp_pos)."""
    rot, pos, w, wd, acc, grasp_rot, grasp_pos, grasp_acc = _forward_pass(
        arrays, w_base, wd_base, acc_base, q, qd, qdd
    )
    to_grasp = grasp_from_base_kernel(grasp_rot, grasp_pos)
    links = _momentum_rate_pass(arrays, rot, pos, w, wd, acc)
    g = arrays.grasp_link
    # Vectors in G: R_G^T v is v @ R_G.
    y = body_regressor_kernel(grasp_acc @ grasp_rot, w[g] @ grasp_rot, wd[g] @ grasp_rot)
    return to_grasp @ links, y, to_grasp, grasp_rot, grasp_pos


@njit(cache=True)
def _balance_jacobians(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, q,
):  # fmt: skip
    """Jacobians of (links_G, Y) in xi = (acc_base, wd_base, qdd) at joint angles q:
    (d links (6, n), d Y (n, 6, 10)), n = 6 + n_joints.

    The frames depend on q alone and every rate term of the two passes (w x (w x r),
    w_p x qd z, w x I w) is constant in xi, so the Jacobians are the passes' acceleration parts,
    written for the columns of xi at once (J_a, J_wd (3, n) per link, e_m the m-th unit row):

        J_wd,0 = [0 I 0],                 J_a,0 = [I 0 0]
        J_wd,k = J_wd,p + z_k e_(6+j),    J_a,k = J_a,p - [r]x J_wd,p
        J_f,k  = m_k (J_a,k - [c_k]x J_wd,k)
        J_n,k  = R_k I_k R_k^T J_wd,k + [p_k + c_k]x J_f,k

    with d links_G = T_GB sum_k [J_f,k; J_n,k]. Y is linear in (a, wd) at w = 0, so column m of
    d Y is Y(R_G^T J_a,G e_m, 0, R_G^T J_wd,g e_m), J_a,G = J_a,g - [r_g]x J_wd,g."""
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    n_links, nj = parent.shape[0], q.shape[0]
    n = 6 + nj
    zero3, zero_j = np.zeros(3), np.zeros(nj)
    frames = _forward_pass(arrays, zero3, zero3, zero3, q, zero_j, zero_j)
    rot, pos, rot_g, pos_g = frames[0], frames[1], frames[5], frames[6]
    jac_wd, jac_a = np.zeros((n_links, 3, n)), np.zeros((n_links, 3, n))
    jac_a[0, :, 0:3] = np.eye(3)
    jac_wd[0, :, 3:6] = np.eye(3)
    for k in range(1, n_links):
        p = parent[k]
        r = rot[p] @ pos_in_parent[k]
        jac_wd[k] = jac_wd[p]
        jac_wd[k, :, 6 + k - 1] += rot[k] @ joint_axis[k]
        jac_a[k] = jac_a[p] - skew(r) @ jac_wd[p]
    d_links = np.zeros((6, n))
    for k in range(n_links):
        c = rot[k] @ com[k]
        jac_f = mass[k] * (jac_a[k] - skew(c) @ jac_wd[k])
        inertia_b = rot[k] @ inertia_com[k] @ np.ascontiguousarray(rot[k].T)
        d_links[:3] += jac_f
        d_links[3:] += inertia_b @ jac_wd[k] + skew(pos[k] + c) @ jac_f
    g = grasp_link
    jac_a_g = jac_a[g] - skew(rot[g] @ grasp_pos) @ jac_wd[g]
    # Rows m of J^T R_G are the columns of R_G^T J: unit-motion vectors in G.
    acc_g = np.ascontiguousarray(jac_a_g.T) @ rot_g
    wd_g = np.ascontiguousarray(jac_wd[g].T) @ rot_g
    d_y = np.empty((n, 6, 10))
    for m in range(n):
        d_y[m] = body_regressor_kernel(acc_g[m], zero3, wd_g[m])
    return grasp_from_base_kernel(rot_g, pos_g) @ d_links, d_y


@njit(cache=True)
def _propagate_batch(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, w_base, wd_base, acc_base, q, qd, qdd,
):  # fmt: skip
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    n, n_links = w_base.shape[0], parent.shape[0]
    rot = np.empty((n, n_links, 3, 3))
    pos, w, wd, acc = [np.empty((n, n_links, 3)) for _ in range(4)]
    g_rot = np.empty((n, 3, 3))
    g_pos, g_acc = np.empty((n, 3)), np.empty((n, 3))
    for i in range(n):
        out = _forward_pass(arrays, w_base[i], wd_base[i], acc_base[i], q[i], qd[i], qdd[i])
        rot[i], pos[i], w[i], wd[i], acc[i], g_rot[i], g_pos[i], g_acc[i] = out
    return rot, pos, w, wd, acc, g_rot, g_pos, g_acc


@njit(cache=True)
def _momentum_rate_batch(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, rot, pos, w, wd, acc,
):  # fmt: skip
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    out = np.empty((rot.shape[0], 6))
    for i in range(rot.shape[0]):
        out[i] = _momentum_rate_pass(arrays, rot[i], pos[i], w[i], wd[i], acc[i])
    return out


@njit(cache=True)
def _body_regressor_batch(acc, w, wd):
    out = np.empty((acc.shape[0], 6, 10))
    for i in range(acc.shape[0]):
        out[i] = body_regressor_kernel(acc[i], w[i], wd[i])
    return out


@njit(cache=True)
def _cargo_regressor_batch(grasp_rot, grasp_pos, grasp_acc, grasp_w, grasp_wd):
    out = np.empty((grasp_rot.shape[0], 6, 10))
    for i in range(grasp_rot.shape[0]):
        rot = grasp_rot[i]
        y = body_regressor_kernel(grasp_acc[i] @ rot, grasp_w[i] @ rot, grasp_wd[i] @ rot)
        out[i] = _wrench_transform(rot, grasp_pos[i]) @ y
    return out


# ------------------------------------------------------------------------ public functions
def _flat(x, trailing: tuple[int, ...], batch: tuple[int, ...], name: str) -> np.ndarray:
    """``x`` as a contiguous float64 array (n, *trailing) for the batch shape ``batch``."""
    a = np.asarray(x, dtype=float)
    if a.shape != (*batch, *trailing):
        raise ValueError(f"{name} must have shape {(*batch, *trailing)}, got {a.shape}")
    return np.ascontiguousarray(a.reshape(-1, *trailing))


def as_single(x, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``x`` as a contiguous float64 array of ``shape`` (one sample, what the compiled kernels
    take); ValueError naming ``name`` for another shape."""
    a = np.asarray(x, dtype=float)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def propagate(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
) -> Kinematics:
    """First pass: base motion and joint motion out to every link and the grasp frame.

    ``w_base``, ``wd_base``: base angular velocity (rad/s) and acceleration (rad/s^2) in B;
    ``acc_base``: acceleration of B's origin (m/s^2) in B; ``q, qd, qdd``: (..., n_joints) rad,
    rad/s, rad/s^2. Leading dimensions are a batch.
    """
    batch = np.shape(w_base)[:-1]
    nj = robot.n_joints
    args = [_flat(x, (3,), batch, name) for x, name in
            ((w_base, "w_base"), (wd_base, "wd_base"), (acc_base, "acc_base"))]  # fmt: skip
    args += [_flat(x, (nj,), batch, name) for x, name in ((q, "q"), (qd, "qd"), (qdd, "qdd"))]
    rot, pos, w, wd, acc, grasp_rot, grasp_pos, grasp_acc = _propagate_batch(*robot.arrays, *args)
    g = robot.grasp_link
    n_links = len(robot.links)
    return Kinematics(
        rot=rot.reshape(*batch, n_links, 3, 3),
        pos=pos.reshape(*batch, n_links, 3),
        w=w.reshape(*batch, n_links, 3),
        wd=wd.reshape(*batch, n_links, 3),
        acc=acc.reshape(*batch, n_links, 3),
        grasp_rot=grasp_rot.reshape(*batch, 3, 3),
        grasp_pos=grasp_pos.reshape(*batch, 3),
        grasp_acc=grasp_acc.reshape(*batch, 3),
        grasp_w=w[:, g].reshape(*batch, 3),
        grasp_wd=wd[:, g].reshape(*batch, 3),
    )


def link_poses(robot: RobotDescription, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every link frame in the base frame at joint angles ``q`` (n_joints,) rad: rotations
    (L, 3, 3) and origins (L, 3) m (``propagate`` at rest)."""
    zero3, zero_j = np.zeros(3), np.zeros(robot.n_joints)
    kin = propagate(robot, zero3, zero3, zero3, q, zero_j, zero_j)
    return kin.rot, kin.pos


def grasp_pose(robot: RobotDescription, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grasp frame G in the base frame at joint angles ``q`` (n_joints,) rad: rotation (3, 3)
    and origin (3,) m (``propagate`` at rest)."""
    return _grasp_pose(*robot.arrays, as_single(q, (robot.n_joints,), "q"))


def link_momentum_rate(robot: RobotDescription, kin: Kinematics) -> np.ndarray:
    """Second pass: sum over the robot's own links of the rate of change of momentum, as a
    wrench in B about B's origin (..., 6): what the robot's bodies absorb of the external
    wrench."""
    batch, n_links = kin.pos.shape[:-2], len(robot.links)
    fields = [_flat(kin.rot, (n_links, 3, 3), batch, "kin.rot")]
    fields += [_flat(getattr(kin, name), (n_links, 3), batch, f"kin.{name}")
               for name in ("pos", "w", "wd", "acc")]  # fmt: skip
    return _momentum_rate_batch(*robot.arrays, *fields).reshape(*batch, 6)


def body_regressor(acc: np.ndarray, w: np.ndarray, wd: np.ndarray) -> np.ndarray:
    """Regressor Y (..., 6, 10) of one rigid body in its own frame: [f; n_o] = Y pi.

    ``acc`` (m/s^2) is the acceleration of the frame origin o, ``w`` (rad/s) / ``wd`` (rad/s^2)
    the angular velocity and acceleration, all in the body frame; pi = [m, h, I_xx, I_yy, I_zz,
    I_xy, I_xz, I_yz] with h = m c and I about o. f = m a + wd x h + w x (w x h);
    n_o = I wd + w x (I w) + h x a. Leading dimensions broadcast.
    """
    acc, w, wd = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (acc, w, wd)))
    batch = acc.shape[:-1]
    flat = [_flat(x, (3,), batch, name) for x, name in ((acc, "acc"), (w, "w"), (wd, "wd"))]
    return _body_regressor_batch(*flat).reshape(*batch, 6, 10)


def wrench_transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """6x6 map of a wrench [f; n about A's origin] in frame A to frame B, where A's pose in B is
    (rot (3, 3), pos (3,) m): f_B = R f, n_B = R n + pos x (R f)."""
    return _wrench_transform(as_single(rot, (3, 3), "rot"), as_single(pos, (3,), "pos"))


def grasp_from_base(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Inverse of ``wrench_transform(rot, pos)``: wrench in B (about B's origin) -> frame G whose
    pose in B is (rot, pos), moments about G's origin: f_G = R^T f, n_G = R^T (n - pos x f)."""
    return grasp_from_base_kernel(as_single(rot, (3, 3), "rot"), as_single(pos, (3,), "pos"))


def cargo_regressor(kin: Kinematics) -> np.ndarray:
    """A (..., 6, 10): the cargo's momentum rate as a wrench in B about B's origin is A pi, with
    pi the cargo's standard parameters in the grasp frame G: A = T_BG Y(R^T a_G, R^T w_G,
    R^T wd_G), R = ``kin.grasp_rot``."""
    batch = kin.grasp_pos.shape[:-1]
    fields = [_flat(kin.grasp_rot, (3, 3), batch, "kin.grasp_rot")]
    fields += [_flat(getattr(kin, name), (3,), batch, f"kin.{name}")
               for name in ("grasp_pos", "grasp_acc", "grasp_w", "grasp_wd")]  # fmt: skip
    return _cargo_regressor_batch(*fields).reshape(*batch, 6, 10)


def thrust_wrench(robot: RobotDescription, command: np.ndarray) -> np.ndarray:
    """Propulsion wrench (..., 6) in B about B's origin from the thrust-site command
    [f (N); tau (N m)] in the thrust-site frame."""
    return np.asarray(command, dtype=float) @ robot.thrust_to_base.T


def _single_motion(robot, w_base, wd_base, acc_base, q, qd, qdd) -> list[np.ndarray]:
    """One sample's motion inputs checked for shape, as the compiled kernels take them."""
    nj = (robot.n_joints,)
    return [as_single(x, shape, name) for x, shape, name in (
        (w_base, (3,), "w_base"), (wd_base, (3,), "wd_base"), (acc_base, (3,), "acc_base"),
        (q, nj, "q"), (qd, nj, "qd"), (qdd, nj, "qdd"),
    )]  # fmt: skip


def balance_in_grasp_frame(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    thrust_base: np.ndarray,
) -> tuple[Balance, np.ndarray, np.ndarray]:
    """One instant's wrench balance in the grasp frame G, and G's pose in B (rotation (3, 3),
    origin (3,) m). Inputs as ``propagate`` for one sample, and the propulsion wrench
    ``thrust_base`` (6,) in B about B's origin. Both passes and the regressor in one compiled
    call: the estimator evaluates it every other control step."""
    inputs = _single_motion(robot, w_base, wd_base, acc_base, q, qd, qdd)
    thrust = as_single(thrust_base, (6,), "thrust_base")
    thrust_g, links_g, y, rot, pos = _grasp_balance(*robot.arrays, *inputs, thrust)
    return Balance(thrust_g, links_g, y), rot, pos


# ---------------------------------------------------------------------------------------------


def links_and_regressor(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(links_G (6,), Y (6, 10)) of one sample: the links' rate of change of momentum and the
    cargo's body regressor in G (moments about G's origin), inputs as ``balance_in_grasp_frame``.
    For w_base, q and qd held both are affine in the motion xi = (acc_base, wd_base, qdd)."""
    inputs = _single_motion(robot, w_base, wd_base, acc_base, q, qd, qdd)
    _, links_g, y, _, _ = _grasp_balance(*robot.arrays, *inputs, np.zeros(6))
    return links_g, y


def balance_motion_jacobians(
    robot: RobotDescription,
    w_base: np.ndarray,
    wd_base: np.ndarray,
    acc_base: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact Jacobians of ``links_and_regressor`` in the motion xi = (acc_base (3), wd_base (3),
    qdd (n_joints)) with w_base, q, qd held: (d links_G / d xi (6, n), d Y / d xi (n, 6, 10)),
    n = 6 + n_joints. Units: links N (or N m) per m/s^2, rad/s^2 of the coordinate. The
    balance is affine in xi with coefficients that depend on q alone (``_balance_jacobians``):
    w_base and qd, checked for shape, do not enter."""
    inputs = _single_motion(robot, w_base, wd_base, acc_base, q, qd, qdd)
    return _balance_jacobians(*robot.arrays, inputs[3])
