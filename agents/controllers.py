"""Cooperative controllers: all robots together track the cargo reference.

The robots and the cargo are treated as one body at the arms' current angles, each robot's arm
at its own angles, and the arms' motion relative to the cargo (from the joint rates) adds its
wrench (``team_dynamics.arm_motion_wrench``). With the composite mass M, centre of mass c and
inertia I_c (robots known, cargo from live estimates, the truth, or nothing), a PD law with
feed-forward
gives the desired acceleration of the cargo frame (Astrobee's law, sources §3.1, docs/design.md:
F = m (a_ref + Kd (v_ref - v) + Kp e_p), and likewise for attitude with e_R = log(R_ref R^T)),
hence the total wrench about c:
    F = M (a + wd x (c - p) + w x (w x (c - p))),     tau = I_c wd + w x I_c w.
The wrench is allocated among the robots through the grasp geometry by the minimum-norm solution
weighted by each robot's propulsion limits; ``CooperativeController`` then scales it down
uniformly if any robot saturates (so the direction of the total wrench is kept), while
``ObservationController`` by default sends the allocation as it is and the env clips each entry
to its limit (measured on figure8_tumble with arm oscillations: uniform scaling starves the
unsaturated axes of feedback and loses the cargo where clipping keeps it), so that the env's
``infos["saturated"]`` shows the share of the wanted thrust that was not delivered. A robot that
has let go of the cargo (its state None) is part of neither the composite body nor the
allocation: the robots still holding share the whole wrench. The equations and their compiled
kernels are in ``team_dynamics``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import log_so3, matmul3_into, matvec3_into
from astrocargo.estimator.inertia import transform_params
from astrocargo.estimator.rne import RobotDescription

from .arm_kinematics import arm_motion_into, arm_work, empty_arm_motions
from .team_dynamics import (
    TeamModel,
    allocate,
    arm_motion_wrench,
    body_from_params,
    body_of_frames,
    composite_body,
    pd_accelerations,
    place_arm_motion,
    place_body,
    place_body_into,
    team_commands,
    team_model,
    team_wrench,
)
from .trajectories import Reference

# Translation: ISS flight-mode gains (iss.config); attitude: gnc.config defaults, which the
# heavier robot-cargo assembly can follow within the propulsion limits (sources §3).
POS_KP, POS_KD = 0.6, 1.2
ATT_KP, ATT_KD = 2.0, 1.6
CARGO_MODELS = ("estimate", "none", "truth")
_NO_CARGO = (0.0, np.zeros(3), np.zeros((3, 3)))


@dataclass(frozen=True)
class RobotState:
    """One robot's base pose (rotation base -> world, position m), arm joint angles (rad) and
    rates (rad/s; None: at rest)."""

    rot: np.ndarray
    pos: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray | None = None


@dataclass(frozen=True)
class CargoState:
    """The cargo frame's pose (rotation, position m) and twist (m/s, rad/s) in world axes."""

    rot: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    w: np.ndarray


def _vector(x, shape: tuple[int, ...]) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=float).reshape(shape)


class CooperativeController:
    """Computes every robot's thrust command from the true (or estimated) team state.

    Args:
        robots: the robots' known models (one arm structure for all).
        pos_kp, pos_kd, att_kp, att_kd: per-unit-mass / per-unit-inertia gains (1/s^2, 1/s).
    """

    def __init__(
        self,
        robots: list[RobotDescription],
        pos_kp: float = POS_KP,
        pos_kd: float = POS_KD,
        att_kp: float = ATT_KP,
        att_kd: float = ATT_KD,
    ) -> None:
        self.robots = list(robots)
        self.gains = (pos_kp, pos_kd, att_kp, att_kd)
        self.team: TeamModel = team_model(self.robots)
        self._gains = np.array(self.gains, dtype=float)
        self.last_ratio = 0.0

    def commands(
        self,
        ref: Reference,
        cargo: CargoState,
        robot_states: list[RobotState | None],
        cargo_params: np.ndarray | None,
    ) -> list[np.ndarray]:
        """Thrust commands (6,) per robot, [force N; torque N m] in each base frame.

        ``robot_states``: one per robot, None for a robot that has let go of the cargo (its
        command is zero). ``cargo_params``: the cargo's standard parameters in the cargo frame,
        or None for no model. ``last_ratio`` keeps the largest command / limit before scaling.
        """
        n = len(self.robots)
        if len(robot_states) != n:
            raise ValueError(
                f"robot_states must hold one entry per robot ({n}), got {len(robot_states)}"
            )
        holding = np.array([i for i, st in enumerate(robot_states) if st is not None], np.int64)
        if not len(holding):
            raise ValueError("no robot holds the cargo: every robot state is None")
        rot_base, pos_base = np.zeros((n, 3, 3)), np.zeros((n, 3))
        q = np.zeros((n, self.team.parent.shape[1] - 1))
        qd = np.zeros_like(q)
        for i in holding:
            st = robot_states[i]
            rot_base[i], pos_base[i], q[i] = st.rot, st.pos, st.joint_pos
            if st.joint_vel is not None:
                qd[i] = st.joint_vel
        rot_c, pos_c = _vector(cargo.rot, (3, 3)), _vector(cargo.pos, (3,))
        body = _NO_CARGO
        if cargo_params is not None:
            mass, com, inertia = body_from_params(_vector(cargo_params, (10,)))
            body = (mass, *place_body(com, inertia, rot_c, pos_c))
        w = _vector(cargo.w, (3,))
        acc, wd = pd_accelerations(
            self._gains,
            _vector(ref.pos, (3,)) - pos_c,
            _vector(ref.vel, (3,)) - _vector(cargo.vel, (3,)),
            log_so3(_vector(ref.rot, (3, 3)) @ rot_c.T),
            _vector(ref.w, (3,)) - w,
            _vector(ref.acc, (3,)),
            _vector(ref.wd, (3,)),
        )
        out, self.last_ratio = team_commands(
            self.team, holding, rot_base, pos_base, q, body, pos_c, w, acc, wd, qd
        )
        return list(out)


class BaseTracking(NamedTuple):
    """The observation blocks the observation controller reads, one row per acting robot, in
    that robot's base frame (see the env's observation layout), and the team's arms as that
    robot sees them (its own encoders and servo-target rates; each peer's from its latest
    message, moved on by the message's age at its rate; its own for a peer not yet heard)."""

    team_joint_pos: np.ndarray  # (k, n, n_joints) rad, every robot's arm
    team_joint_vel: np.ndarray  # (k, n, n_joints) rad/s
    base_pos_err: np.ndarray  # (k, 3) m, base minus its reference
    base_vel_err: np.ndarray  # (k, 3) m/s
    base_att_err: np.ndarray  # (k, 3) rad, log(R_ref^T R)
    base_ang_vel: np.ndarray  # (k, 3) rad/s
    ref_acc: np.ndarray  # (k, 3) m/s^2 of the cargo reference (its origin)
    ref_ang_vel: np.ndarray  # (k, 3) rad/s
    ref_ang_acc: np.ndarray  # (k, 3) rad/s^2
    ref_pan: np.ndarray  # (k, 2) rad, rad/s: pan ramp angle and rate
    cargo_params: np.ndarray  # (k, 10) cargo's standard parameters in the robot's grasp frame


# The blocks of ``BaseTracking`` read from the observation as they are.
_OBSERVED_BLOCKS = BaseTracking._fields[2:-1]


class ObservedColumns(NamedTuple):
    """Where ``BaseTracking``'s blocks lie in an observation (the env's layout), as
    [start, stop) column pairs; (-1, -1) for a block the layout lacks."""

    blocks: np.ndarray  # (8, 2) int64, the ``_OBSERVED_BLOCKS`` in order
    joint_pos: np.ndarray  # (2,) int64, the robot's own arm angles
    joint_vel: np.ndarray  # (2,) int64, its servo-target rates ((-1, -1): arms at rest)
    estimate: np.ndarray  # (2,) int64, its cargo estimate ((-1, -1): fixed parameters)
    peer_slots: np.ndarray  # (n, n-1, 5) int64, ``ObservationController._peer_slot_columns``


@njit(cache=True)
def _peer_arms(
    obs: np.ndarray, acting: np.ndarray, slots: np.ndarray, q: np.ndarray, qd: np.ndarray
) -> None:
    """Each peer arm heard by the acting robot a (observation obs[a]): q[a, j] = q_j + qd_j age,
    qd[a, j] = qd_j, from the message slots of robot acting[a] (``slots`` (n, n-1, 5): peer j,
    valid, age, first joint angle and first joint rate columns); the others left as they are."""
    for a in range(len(acting)):
        for p in range(slots.shape[1]):
            j, valid, age, joint_pos, joint_vel = slots[acting[a], p]
            if obs[a, valid] > 0:
                for c in range(q.shape[2]):
                    rate = obs[a, joint_vel + c]
                    q[a, j, c] = obs[a, joint_pos + c] + rate * obs[a, age]
                    qd[a, j, c] = rate


@njit(cache=True)
def _observed_tracking(
    obs: np.ndarray,
    acting: np.ndarray,
    columns: ObservedColumns,
    n_robots: int,
    fixed_params: np.ndarray,
) -> BaseTracking:
    """``BaseTracking`` of the robots ``acting`` from their observations obs (k, obs_dim): each
    block copied from its columns; every robot's arm at the acting robot's own angles and
    rates (zero rates without joint_vel columns), then each heard peer's from its message
    (``_peer_arms``); the cargo parameters from the estimate's columns, or ``fixed_params``
    (n, 10) of each acting robot where the layout gives none."""
    k, (q_start, q_stop), (qd_start, qd_stop) = len(acting), columns.joint_pos, columns.joint_vel
    q = np.empty((k, n_robots, q_stop - q_start))
    qd = np.zeros_like(q)
    for a in range(k):
        for j in range(n_robots):
            q[a, j] = obs[a, q_start:q_stop]
            if qd_start >= 0:
                qd[a, j] = obs[a, qd_start:qd_stop]
    _peer_arms(obs, acting, columns.peer_slots, q, qd)
    spans = columns.blocks
    if columns.estimate[0] >= 0:
        params = np.ascontiguousarray(obs[:, columns.estimate[0] : columns.estimate[1]])
    else:
        params = fixed_params[acting]
    b = [np.ascontiguousarray(obs[:, spans[i, 0] : spans[i, 1]]) for i in range(len(spans))]
    return BaseTracking(q, qd, b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], params)


@njit(cache=True)
def _equal_rows(table: np.ndarray, r: int, s: int) -> bool:
    """Whether rows r and s of the integer table are equal (``np.array_equal`` of the two
    rows, without its temporary arrays)."""
    for c in range(table.shape[1]):
        if table[r, c] != table[s, c]:
            return False
    return True


@njit(cache=True)
def _team_views(team: TeamModel, holding: np.ndarray, q: np.ndarray, qd: np.ndarray) -> tuple:
    """The arms of the robots ``holding`` as each acting robot a sees them (q, qd (k, n,
    n_joints)), each distinct (model, q[a, j], qd[a, j]) worked out once (equal bit for bit,
    as when every robot has heard every peer's latest message): row (k, n), robot j seen by a
    being row[a, j] of the stacked ``robot_body`` results (masses, centres, inertias, grasp
    rotations, grasp origins, base frame) and ``arm_motion_in_grasp`` results (motions)."""
    k, n_joints = q.shape[0], q.shape[2]
    count = k * len(holding)
    keys = np.empty((count, 1 + 2 * n_joints))
    bodies = (np.empty(count), np.empty((count, 3)), np.empty((count, 3, 3)))
    grasps = (np.empty((count, 3, 3)), np.empty((count, 3)))
    motions = empty_arm_motions(count, team.parent.shape[1])
    work = arm_work(team.parent.shape[1])
    row = np.zeros((k, q.shape[1]), dtype=np.int64)
    used = 0
    for a in range(k):
        for idx in range(len(holding)):
            j = holding[idx]
            m = team.model_of[j]
            keys[used, 0] = m
            keys[used, 1 : 1 + n_joints], keys[used, 1 + n_joints :] = q[a, j], qd[a, j]
            bits = keys[: used + 1].view(np.int64)
            r = 0
            while r < used and not _equal_rows(bits, r, used):
                r += 1
            row[a, j] = r
            if r == used:  # the body from the motion's link frames at q
                arm_motion_into(motions, r, team, m, q[a, j], qd[a, j], work)
                body = body_of_frames(team, m, work.rots[0], work.poss[0])
                bodies[0][r], bodies[1][r], bodies[2][r] = body[:3]
                grasps[0][r], grasps[1][r] = body[3:]
                used += 1
    return row, bodies, grasps, motions


@njit(cache=True)
def _team_in_cargo(
    handrail_rot: np.ndarray,
    handrail_pos: np.ndarray,
    holding: np.ndarray,
    robot_bodies: tuple,
    grasps: tuple,
    row: np.ndarray,
) -> tuple:
    """The team in the cargo frame C, robot j's body and grasp frame (R_bg, p_bg) in its base
    at row[j] of ``robot_bodies`` and ``grasps`` (``_team_views``): the bases of the robots
    ``holding`` (rotations (n, 3, 3), origins (n, 3), zeros for the others) and the bodies of
    those robots with one more slot for the cargo (masses, centres, inertias). Base j in C:
    R_cb = R_ch R_bg^T, p_cb = p_ch - R_cb p_bg (handrail j's pose (R_ch, p_ch) in C)."""
    n, count = len(handrail_rot), len(holding) + 1
    rot_base, pos_base = np.zeros((n, 3, 3)), np.zeros((n, 3))
    masses, coms, inertias = np.zeros(count), np.zeros((count, 3)), np.zeros((count, 3, 3))
    scratch = np.empty((3, 3))
    for idx in range(len(holding)):
        j = holding[idx]
        r = row[j]
        matmul3_into(rot_base[j], handrail_rot[j], grasps[0][r].T)
        matvec3_into(pos_base[j], rot_base[j], grasps[1][r])
        for i in range(3):
            pos_base[j, i] = handrail_pos[j, i] - pos_base[j, i]
        masses[idx] = robot_bodies[0][r]
        place_body_into(
            coms[idx], inertias[idx], robot_bodies[1][r], robot_bodies[2][r], rot_base[j],
            pos_base[j], scratch,
        )  # fmt: skip
    return rot_base, pos_base, (masses, coms, inertias)


@njit(cache=True)
def _cargo_motion(
    gains: np.ndarray,
    obs: BaseTracking,
    a: int,
    rot_cb: np.ndarray,
    base_vel_rel: np.ndarray,
    base_w_rel: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cargo's angular velocity w and desired accelerations (``pd_accelerations``) as
    acting robot a sees them in the cargo frame C (its base axes rotated by R_cb, base a's pose
    in C at its arm angles): the cargo's twist is the base's less the base's motion relative to
    the cargo (v_rel, w_rel, ``team_arm_motion``): w = R_cb w_base - w_rel, velocity error at
    the base point R_cb base_vel_err - v_rel; position and attitude errors are the base's (the
    grasp is rigid at the measured angles): e_p = -R_cb base_pos_err, e_R = -R_cb
    base_att_err; the reference acceleration of the cargo origin is ref_acc."""
    blocks = (obs.base_ang_vel, obs.base_vel_err, obs.base_pos_err, obs.base_att_err,
              obs.ref_ang_vel, obs.ref_acc, obs.ref_ang_acc)  # fmt: skip
    rotated = np.empty((len(blocks), 3))  # each block in C's axes
    for b in range(len(blocks)):
        matvec3_into(rotated[b], rot_cb, blocks[b][a])
    w = rotated[0] - base_w_rel
    vel_err = rotated[1] - base_vel_rel
    acc, wd = pd_accelerations(
        gains, -rotated[2], -vel_err, -rotated[3], rotated[4] - w, rotated[5], rotated[6]
    )
    return w, acc, wd


@njit(cache=True)
def _observation_actions(
    team: TeamModel,
    handrail_rot: np.ndarray,
    handrail_pos: np.ndarray,
    gains: np.ndarray,
    arm_scale_rad: float,
    acting: np.ndarray,
    holding: np.ndarray,
    observations: np.ndarray,
    columns: ObservedColumns,
    fixed_params: np.ndarray,
    with_cargo: bool,
    scale_down: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Actions (k, 8) of the acting robots (all holding the cargo), from their observations
    (k, obs_dim) read as ``_observed_tracking``: thrust u / thrust_limit, tilt offset 0, pan
    offset clip(ref_pan / arm_scale_rad, -1, 1); and each one's saturation ratio (largest |u| /
    limit of the allocation before scaling). Robot i works in the cargo frame C, every robot at
    the arm angles i sees, the cargo's motion from i's base (``_cargo_motion``). The wrench is
    ``team_wrench`` about the team's centre of mass plus ``arm_motion_wrench`` of the arms'
    motion, allocated by ``allocate``; with ``scale_down`` False the commands are the
    allocation's before its scaling (the env then clips each entry to its limit)."""
    out, ratios, origin = np.zeros((len(acting), 8)), np.zeros(len(acting)), np.zeros(3)
    obs = _observed_tracking(observations, acting, columns, len(handrail_rot), fixed_params)
    row, robot_bodies, grasps, motions = _team_views(
        team, holding, obs.team_joint_pos, obs.team_joint_vel
    )
    placed = -1  # the acting robot whose view of the team is placed in C
    for a in range(len(acting)):
        i = acting[a]
        if placed < 0 or not _equal_rows(row, a, placed):
            rot_base, pos_base, bodies = _team_in_cargo(
                handrail_rot, handrail_pos, holding, robot_bodies, grasps, row[a]
            )
            arms = place_arm_motion(team, holding, handrail_rot, handrail_pos, motions, row[a])
            placed = a
        masses, coms, inertias = bodies
        if with_cargo:  # the cargo's slot, this robot's estimate
            mass, com, inertia = body_from_params(obs.cargo_params[a])
            masses[-1] = mass
            coms[-1], inertias[-1] = place_body(com, inertia, handrail_rot[i], handrail_pos[i])
        w, acc, wd = _cargo_motion(gains, obs, a, rot_base[i], arms[7][i], arms[8][i])
        mass, com, inertia = composite_body(masses, coms, inertias)
        wrench = team_wrench(mass, com, inertia, origin, w, acc, wd)
        wrench += arm_motion_wrench(*arms[:7], com, w)
        commands, ratios[a] = allocate(team, holding, rot_base, pos_base, com, wrench)
        out[a, :6] = commands[i] / team.thrust_limit[i]
        if not scale_down:
            out[a, :6] *= max(ratios[a], 1.0)
        out[a, 7] = min(max(obs.ref_pan[a, 0] / arm_scale_rad, -1.0), 1.0)
    return out, ratios


class ObservationController:
    """The cooperative controller driven by the env's observations only, scored like a policy.

    Each robot works out the team's wrench from its own observation, in the cargo frame: its
    base tracking errors stand for the cargo's (the grasp is rigid at the measured angles), its
    base's twist less the base's motion relative to the cargo from its own arm rates is the
    cargo's, the cargo and the other robots are placed by the known grasp geometry (handrail
    poses on the cargo; each peer's arm at the angles and rates of its latest message, moved on
    by the message's age, or at this robot's own before the first), the arms' motion adds its
    wrench, and the cargo's inertia comes from ``cargo_model``: "estimate" (this robot's own
    live estimate, from the observation, in its grasp frame), "none" (no cargo), or "truth"
    (``truth_params``, cargo frame, for comparison only). It then applies its share of the
    allocation (``_observation_actions``), unscaled unless ``scale_down`` (module docstring),
    and sends the arm targets of the reference pan ramp. ``last_ratios``: each acting robot's
    largest command / limit of the last call.

    ``predict(obs)`` takes the env's observation dict (agent -> obs) or an array (n_robots,
    obs_dim) in agent order and returns actions of the same form, with SB3's signature. The
    agents of a dict are the robots holding the cargo: the team's wrench is shared among them
    only. After a robot has let go (the env's ``release_at``), pass the observations of the
    agents still acting, ``{a: obs[a] for a in env.agents}``: the dict the env returns at the
    release step still holds the released robot's final observation.
    """

    def __init__(
        self,
        robots: list[RobotDescription],
        handrail_poses: list[tuple[np.ndarray, np.ndarray]],
        layout: dict[str, slice],
        cargo_model: str = "estimate",
        truth_params: np.ndarray | None = None,
        arm_offset_scale_rad: float = 0.5,
        agents: list[str] | None = None,
        scale_down: bool = False,
    ) -> None:
        if cargo_model not in CARGO_MODELS:
            raise ValueError(f"cargo_model must be one of {CARGO_MODELS}, got {cargo_model!r}")
        if cargo_model == "truth" and truth_params is None:
            raise ValueError('cargo_model="truth" needs truth_params (cargo frame)')
        if cargo_model == "estimate" and "estimate_mean" not in layout:
            raise ValueError('cargo_model="estimate" needs observe_estimates=True in the env')
        self.robots = list(robots)
        if len(handrail_poses) != len(self.robots):
            raise ValueError(f"handrail_poses must hold one pose per robot ({len(self.robots)})")
        self.handrail_poses = [(np.asarray(r), np.asarray(p)) for r, p in handrail_poses]
        self.layout = layout
        self.cargo_model = cargo_model
        self.truth_params = None if truth_params is None else np.asarray(truth_params, float)
        self.arm_scale = float(arm_offset_scale_rad)
        self.scale_down = bool(scale_down)
        self.last_ratios = np.zeros(0)
        self.team = CooperativeController(self.robots)
        self._handrail_rot = _vector([r for r, _ in self.handrail_poses], (-1, 3, 3))
        self._handrail_pos = _vector([p for _, p in self.handrail_poses], (-1, 3))
        # The truth in each robot's grasp frame (the cargo frame in it: R_ch^T, -R_ch^T p_ch).
        self._truth_in_grasp = np.zeros((len(self.robots), 10))
        if self.truth_params is not None:
            rot_hc = np.swapaxes(self._handrail_rot, -1, -2)
            pos_hc = -np.einsum("nij,nj->ni", rot_hc, self._handrail_pos)
            self._truth_in_grasp = transform_params(self.truth_params, rot_hc, pos_hc)
        # Agent name -> robot index (the env's possible_agents, in robot order).
        names = agents if agents is not None else [f"astrobee_{i}" for i in range(len(robots))]
        if len(names) != len(self.robots):
            raise ValueError(f"agents must name the {len(self.robots)} robots, got {names!r}")
        self.robot_index = {name: i for i, name in enumerate(names)}
        self._columns = self._observed_columns()
        self._acting: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray]] = {}

    @classmethod
    def for_env(cls, env, cargo_model: str = "estimate", **kwargs: Any) -> ObservationController:
        """Build from an ``AstrobeeCargoEnv`` (geometry; the truth only for "truth");
        ``kwargs``: the constructor's other arguments (``scale_down``)."""
        sim = env.sim
        truth = sim.world.cargo_params() if cargo_model == "truth" else None
        return cls(
            sim.robots,
            sim.handrail_pose,
            sim.obs_layout,
            cargo_model,
            truth,
            agents=list(env.possible_agents),
            **kwargs,
        )

    def _peer_slot_columns(self) -> np.ndarray:
        """Per robot i, its peers' arm message slots in the observation (n, n-1, 5): peer j,
        valid column, age column, first joint angle column, first joint rate column, the peers
        in robot order (no slots for a layout without peer arms)."""
        lay, n = self.layout, len(self.robots)
        if "peer0_joint_pos" not in lay:
            return np.zeros((n, 0, 5), dtype=np.int64)
        names = ("valid", "age", "joint_pos", "joint_vel")
        slots = [
            [[j, *(lay[f"peer{p}_{name}"].start for name in names)]
             for p, j in enumerate(j for j in range(n) if j != i)]
            for i in range(n)
        ]  # fmt: skip
        return np.array(slots, dtype=np.int64)

    def _observed_columns(self) -> ObservedColumns:
        """The layout's columns of ``BaseTracking``'s blocks (``ObservedColumns``)."""
        lay, absent = self.layout, slice(-1, -1)

        def span_of(block: slice) -> np.ndarray:
            return np.array([block.start, block.stop], dtype=np.int64)

        def span(name: str) -> np.ndarray:
            return span_of(lay.get(name, absent))

        # Fixed cargo parameters ("true", "none"): no estimate columns are read.
        estimate = span("estimate_mean") if self.cargo_model == "estimate" else span_of(absent)
        return ObservedColumns(
            np.stack([span(name) for name in _OBSERVED_BLOCKS]),
            span("joint_pos"),
            span("joint_vel"),
            estimate,
            self._peer_slot_columns(),
        )

    def _actions(self, acting: np.ndarray, holding: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """Actions (k, 8) of the robots ``acting`` (all holding the cargo; ``holding``: the same,
        sorted) from their observations (k, obs_dim) (``_observation_actions``);
        ``last_ratios`` keeps each one's saturation ratio."""
        actions, self.last_ratios = _observation_actions(
            self.team.team,
            self._handrail_rot,
            self._handrail_pos,
            self.team._gains,
            self.arm_scale,
            acting,
            holding,
            obs,
            self._columns,
            self._truth_in_grasp,
            self.cargo_model != "none",
            self.scale_down,
        )
        return actions

    def _acting_robots(self, agents: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """The robots of the named agents, in their order and sorted (made once per set)."""
        if agents not in self._acting:
            unknown = [a for a in agents if a not in self.robot_index]
            if unknown:
                raise ValueError(f"unknown agents {unknown}; agents: {list(self.robot_index)}")
            acting = np.array([self.robot_index[a] for a in agents], dtype=np.int64)
            self._acting[agents] = acting, np.sort(acting)
        return self._acting[agents]

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        """SB3's signature: returns (actions, state)."""
        del episode_start, deterministic
        if isinstance(observation, dict):
            acting, holding = self._acting_robots(tuple(observation))
            obs = np.array(list(observation.values()), dtype=float)  # (k, obs_dim)
            actions = self._actions(acting, holding, obs)
            return dict(zip(observation, actions, strict=True)), state
        obs = np.asarray(observation, dtype=float)
        if obs.ndim != 2 or obs.shape[0] != len(self.robots):
            raise ValueError(
                f"observation must be a dict or an array ({len(self.robots)}, obs_dim), "
                f"got shape {obs.shape}"
            )
        every = np.arange(len(self.robots), dtype=np.int64)
        return self._actions(every, every, obs), state
