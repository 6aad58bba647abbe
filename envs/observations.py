"""The observations: one table of blocks (name, size) from which the layout, the observation
space's bounds and every robot's observation row are built (the env docstring's Observation
Space section describes each block).

Frames: R (3, 3) maps the robot's base frame (its own estimate) to the world; every vector of
a block is in that base frame, R^T x. The base reference is the pose the base would have if the
cargo were on its reference with the grasp rigid at the measured arm angles q:
R_ref = R_c,ref R_ch G(q)^T, p_ref = p_c,ref + R_c,ref p_ch - R_ref g(q),
v_ref = v_c,ref + w_c,ref x (p_ref - p_c,ref), with (R_ch, p_ch) the handrail in the cargo frame
and (G(q), g(q)) the grasp frame in the base frame (the estimator's forward kinematics of the
arm chain, ``rne.grasp_pose_into``).
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import cross3_into, log_so3_into, matmul3_into, matvec3_into
from astrocargo.estimator.rne import RobotDescription, grasp_pose_into

# The robot's own blocks, in order: (name, size). The kernel below fills them by name through
# the layout's starts (OWN_BLOCKS order is the order of its `values` list).
OWN_BLOCKS = (
    ("base_pos_err", 3),  # base position minus its reference position, m
    ("base_vel_err", 3),  # base velocity minus its reference velocity, m/s
    ("base_att_err", 3),  # rotation vector of R_ref^T R, rad
    ("base_ang_vel", 3),  # gyro, period mean, rad/s
    ("joint_pos", 2),  # encoders tilt, pan, rad
    ("joint_target", 2),  # servo targets tilt, pan, rad
    ("ref_pos_rel", 3),  # cargo reference position minus base position, m
    ("ref_vel", 3),  # cargo reference velocity, m/s
    ("ref_acc", 3),  # cargo reference acceleration, m/s^2
    ("ref_ang_vel", 3),  # cargo reference angular velocity, rad/s
    ("ref_ang_acc", 3),  # cargo reference angular acceleration, rad/s^2
    ("ref_pan", 2),  # reference pan angle and rate, rad, rad/s
    ("joint_vel", 2),  # arm joint rates tilt, pan: the servo targets' rate this step, rad/s
)
# Per peer slot p (peers in increasing index, skipping the robot itself): "peer{p}_" + name.
# joint_pos / joint_vel: the peer's encoder angles and servo-target rates when it sent the message.
PEER_BLOCKS = (("wrench", 6), ("age", 1), ("valid", 1), ("joint_pos", 2), ("joint_vel", 2))
ESTIMATE_BLOCKS = (("estimate_mean", 10), ("estimate_std", 10))


def observation_layout(n_robots: int, observe_estimates: bool = True) -> dict[str, slice]:
    """Index slices of each observation block (see the module docstring's table)."""
    sizes = list(OWN_BLOCKS)
    for p in range(n_robots - 1):
        sizes += [(f"peer{p}_{name}", size) for name, size in PEER_BLOCKS]
    if observe_estimates:
        sizes += list(ESTIMATE_BLOCKS)
    out, start = {}, 0
    for name, size in sizes:
        out[name] = slice(start, start + size)
        start += size
    out["all"] = slice(0, start)
    return out


def observation_bounds(layout: dict[str, slice]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the observation space: the valid flags in [0, 1], the rest
    unbounded."""
    size = layout["all"].stop
    low, high = np.full(size, -np.inf), np.full(size, np.inf)
    for name, sl in layout.items():
        if name.endswith("_valid"):
            low[sl], high[sl] = 0.0, 1.0
    return low, high


@njit(cache=True, inline="always")
def _add_to(out, a, b):
    """out = a + b (3-vectors), written into ``out`` without a temporary (``out`` may be a or
    b)."""
    for i in range(3):
        out[i] = a[i] + b[i]


@njit(cache=True, inline="always")
def _put(row, start, value):
    """row[start : start + len(value)] = value."""
    for k in range(value.shape[0]):
        row[start + k] = value[k]


@njit(cache=True, inline="always")
def _put_in_base(row, start, rot, a, b):
    """row[start : start + 3] = R^T (a - b): a difference of world vectors in base axes (as
    ``matvec3(rot.T, a - b)``, without temporaries)."""
    for i in range(3):
        total = 0.0
        for k in range(3):
            total += rot[k, i] * (a[k] - b[k])
        row[start + i] = total


@njit(cache=True, inline="always")
def _own_blocks(out, starts, rot, base_pos, base_vel, w, q, target, rot_ref, pos_ref, vel_ref,
                ref_vecs, ref_pan, qd, zero, work_rot, work_vec):  # fmt: skip
    """Write the OWN_BLOCKS of one row at ``starts`` (in OWN_BLOCKS order); ref_vecs rows: the
    cargo reference's position, velocity, acceleration, angular velocity and angular
    acceleration (world); ``zero``: a zero 3-vector; ``work_rot`` (3, 3), ``work_vec`` (3,):
    scratch."""
    _put_in_base(out, starts[0], rot, base_pos, pos_ref)
    _put_in_base(out, starts[1], rot, base_vel, vel_ref)
    matmul3_into(work_rot, rot_ref.T, rot)
    log_so3_into(work_vec, work_rot)
    _put(out, starts[2], work_vec)
    _put(out, starts[3], w)
    _put(out, starts[4], q)
    _put(out, starts[5], target)
    _put_in_base(out, starts[6], rot, ref_vecs[0], base_pos)
    for block in range(1, 5):  # the reference's velocity ... angular acceleration
        _put_in_base(out, starts[6 + block], rot, ref_vecs[block], zero)
    _put(out, starts[11], ref_pan)
    _put(out, starts[12], qd)


@functools.cache  # one dtype object per chain length: numba dispatches on it fastest
def arm_dtype(n_links: int) -> np.dtype:
    """One robot's known arm chain and handrail as a record (``ObservationBuilder.arms``):
    each link's rotation, position (in its parent) and joint axis (a zero axis for the base,
    link 0), the grasp frame in its link, the handrail (its grasp site) in the cargo frame."""
    return np.dtype(
        [
            ("link_rot", "f8", (n_links, 3, 3)),
            ("link_pos", "f8", (n_links, 3)),
            ("link_axis", "f8", (n_links, 3)),
            ("grasp_link", "i8"),
            ("grasp_rot", "f8", (3, 3)),
            ("grasp_pos", "f8", 3),
            ("handrail_rot", "f8", (3, 3)),
            ("handrail_pos", "f8", 3),
        ],
        align=True,
    )


@njit(cache=True)
def assemble(out, acting, own_starts, peer_starts, estimate_start, link_parent, arms, nav, q,
             target, ref_rot, ref_vecs, ref_pan, peer_wrench, peer_age, peer_valid, estimates, qd,
             peer_arm):  # fmt: skip
    """Every acting robot's observation row into ``out`` (N, obs_dim); the others' rows are left
    as they are. Robots are rows of the (N, ...) inputs: ``arms`` (``arm_dtype``), ``nav`` (the
    navigation filters, ``navigation.FILTER_DTYPE``: rot, base_pos, base_vel, w_base); peer_*
    (N, P, ...) hold the latest message of each peer slot (wrench in world axes; peer_arm
    (N, P, 4): the sender's arm angles and rates); estimates (N, 20) or (N, 0); qd (N, 2) the
    own arm rates."""
    n_links = link_parent.shape[0]
    # Work arrays, allocated once per call: the arm chain's link poses and levers
    # (grasp_pose_into), the grasp frame G, the base reference's rotation and a scratch; the
    # vectors likewise.
    rots = np.empty((n_links + 4, 3, 3))
    g_rot, rot_ref, scratch = rots[n_links + 1], rots[n_links + 2], rots[n_links + 3]
    vecs = np.zeros((2 * n_links + 8, 3))
    poss, links_lever, zero = vecs[:n_links], vecs[n_links : 2 * n_links + 1], vecs[2 * n_links + 1]
    g_pos, rail, grasp = vecs[2 * n_links + 2], vecs[2 * n_links + 3], vecs[2 * n_links + 4]
    pos_ref, vel_ref, lever = vecs[2 * n_links + 5], vecs[2 * n_links + 6], vecs[2 * n_links + 7]
    for i in range(out.shape[0]):
        if not acting[i]:
            continue
        a, f = arms[i], nav[i]
        grasp_pose_into(
            g_rot, g_pos, rots[: n_links + 1], poss, links_lever, link_parent, a.link_axis,
            a.link_rot, a.link_pos, a.grasp_link, a.grasp_rot, a.grasp_pos, q[i],
        )  # fmt: skip
        matmul3_into(scratch, ref_rot, a.handrail_rot)
        matmul3_into(rot_ref, scratch, g_rot.T)
        matvec3_into(rail, ref_rot, a.handrail_pos)
        matvec3_into(grasp, rot_ref, g_pos)
        for k in range(3):
            pos_ref[k] = ref_vecs[0, k] + rail[k] - grasp[k]
            lever[k] = pos_ref[k] - ref_vecs[0, k]
        cross3_into(rail, ref_vecs[3], lever)
        _add_to(vel_ref, ref_vecs[1], rail)
        row = out[i]
        _own_blocks(
            row, own_starts, f.rot, f.base_pos, f.base_vel, f.w_base, q[i], target[i], rot_ref,
            pos_ref, vel_ref, ref_vecs, ref_pan, qd[i], zero, scratch, grasp,
        )  # fmt: skip
        for p in range(peer_starts.shape[0]):
            s_wrench, s_age, s_valid = peer_starts[p, 0], peer_starts[p, 1], peer_starts[p, 2]
            _put_in_base(row, s_wrench, f.rot, peer_wrench[i, p, :3], zero)
            _put_in_base(row, s_wrench + 3, f.rot, peer_wrench[i, p, 3:], zero)
            row[s_age] = peer_age[i, p]
            row[s_valid] = peer_valid[i, p]
            _put(row, peer_starts[p, 3], peer_arm[i, p, :2])
            _put(row, peer_starts[p, 4], peer_arm[i, p, 2:])
        if estimates.shape[1] > 0:
            _put(row, estimate_start, estimates[i])


class ObservationBuilder:
    """The team's observations from the layout: the robots' known arm models and handrails are
    packed once; ``build`` fills the rows of the acting robots each step."""

    def __init__(
        self,
        layout: dict[str, slice],
        robots: list[RobotDescription],
        handrail_pose: list[tuple[np.ndarray, np.ndarray]],
    ) -> None:
        n = len(robots)
        self.layout, self.obs_dim = layout, layout["all"].stop
        self.own_starts = np.array([layout[name].start for name, _ in OWN_BLOCKS])
        self.peer_starts = np.array(
            [[layout[f"peer{p}_{name}"].start for name, _ in PEER_BLOCKS] for p in range(n - 1)],
            dtype=np.int64,
        ).reshape(n - 1, len(PEER_BLOCKS))
        self.estimate_start = layout["estimate_mean"].start if "estimate_mean" in layout else 0
        links = robots[0].links
        self.link_parent = np.array([link.parent for link in links], dtype=np.int64)
        self.arms = np.zeros(n, dtype=arm_dtype(len(links)))
        for arm, robot, (rail_rot, rail_pos) in zip(self.arms, robots, handrail_pose, strict=True):
            arm["link_rot"] = [k.rot_in_parent for k in robot.links]
            arm["link_pos"] = [k.pos_in_parent for k in robot.links]
            arm["link_axis"] = [  # the base (link 0) has no joint: a zero axis
                np.zeros(3) if k.joint_axis is None else k.joint_axis for k in robot.links
            ]
            arm["grasp_link"], arm["grasp_rot"] = robot.grasp_link, robot.grasp_rot
            arm["grasp_pos"], arm["handrail_rot"], arm["handrail_pos"] = (
                robot.grasp_pos, rail_rot, rail_pos,
            )  # fmt: skip

    def build(self, acting, nav, q, target, ref_rot, ref_vecs, ref_pan, peer_wrench, peer_age,
              peer_valid, estimates, qd=None, peer_arm=None) -> np.ndarray:  # fmt: skip
        """(N, obs_dim) observations: the rows of the ``acting`` robots (bool (N,)), zeros
        elsewhere; ``nav``: the navigation filters (``navigation.FILTER_DTYPE``)."""
        out = np.zeros((len(acting), self.obs_dim))
        n = len(acting)
        qd = np.zeros((n, 2)) if qd is None else qd
        peer_arm = np.zeros((n, max(n - 1, 0), 4)) if peer_arm is None else peer_arm
        assemble(
            out, acting, self.own_starts, self.peer_starts, self.estimate_start,
            self.link_parent, self.arms, nav, q, target, ref_rot, ref_vecs, ref_pan, peer_wrench,
            peer_age, peer_valid, estimates, qd, peer_arm,
        )  # fmt: skip
        return out
