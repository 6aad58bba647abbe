"""Cooperative controllers: all robots together track the cargo reference.

The robots and the cargo are treated as one rigid body (the arms move slowly; their own motion
is a disturbance the feedback absorbs). With the composite mass M, centre of mass c and inertia
I_c (robots known, cargo from live estimates, the truth, or nothing), a PD law with feed-forward
gives the desired acceleration of the cargo frame (Astrobee's law, facts file section 3.1:
F = m (a_ref + Kd (v_ref - v) + Kp e_p), and likewise for attitude with e_R = log(R_ref R^T)),
hence the total wrench about c:
    F = M (a + wd x (c - p) + w x (w x (c - p))),     tau = I_c wd + w x I_c w.
The wrench is allocated among the robots through the grasp geometry by the minimum-norm solution
weighted by each robot's propulsion limits, then scaled down uniformly if any robot saturates (so
the direction of the total wrench is kept). A robot that has let go of the cargo (its state None)
is part of neither the composite body nor the allocation: the robots still holding share the
whole wrench. The equations and their compiled kernels are in ``team_dynamics``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import log_so3
from astrocargo.estimator.inertia import transform_params
from astrocargo.estimator.rne import RobotDescription

from .team_dynamics import (
    TeamModel,
    body_from_params,
    pd_accelerations,
    place_body,
    robot_body,
    team_commands,
    team_model,
    thrust_commands,
)
from .trajectories import Reference

# Translation: ISS flight-mode gains (iss.config); attitude: gnc.config defaults, which the
# heavier robot-cargo assembly can follow within the propulsion limits (facts section 3.2).
POS_KP, POS_KD = 0.6, 1.2
ATT_KP, ATT_KD = 2.0, 1.6
CARGO_MODELS = ("estimate", "none", "truth")
_NO_CARGO = (0.0, np.zeros(3), np.zeros((3, 3)))


@dataclass(frozen=True)
class RobotState:
    """One robot's base pose (rotation base -> world, position m) and arm joint angles (rad)."""

    rot: np.ndarray
    pos: np.ndarray
    joint_pos: np.ndarray


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
        for i in holding:
            st = robot_states[i]
            rot_base[i], pos_base[i], q[i] = st.rot, st.pos, st.joint_pos
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
            self.team, holding, rot_base, pos_base, q, body, pos_c, w, acc, wd
        )
        return list(out)


class BaseTracking(NamedTuple):
    """The observation blocks the observation controller reads, one row per acting robot, in
    that robot's base frame (see the env's observation layout)."""

    joint_pos: np.ndarray  # (k, n_joints) rad
    base_pos_err: np.ndarray  # (k, 3) m, base minus its reference
    base_vel_err: np.ndarray  # (k, 3) m/s
    base_att_err: np.ndarray  # (k, 3) rad, log(R_ref^T R)
    base_ang_vel: np.ndarray  # (k, 3) rad/s
    ref_pos_rel: np.ndarray  # (k, 3) m, cargo reference minus base
    ref_acc: np.ndarray  # (k, 3) m/s^2 of the cargo reference
    ref_ang_vel: np.ndarray  # (k, 3) rad/s
    ref_ang_acc: np.ndarray  # (k, 3) rad/s^2
    ref_pan: np.ndarray  # (k, 2) rad, rad/s: pan ramp angle and rate
    cargo_params: np.ndarray  # (k, 10) cargo's standard parameters in the robot's grasp frame


@njit(cache=True)
def _team_in_base(
    team: TeamModel,
    handrail_rot: np.ndarray,
    handrail_pos: np.ndarray,
    i: int,
    holding: np.ndarray,
    q: np.ndarray,
) -> tuple:
    """Robot i's view of the team in its base frame B_i, every arm at i's angles q: the bases
    of the robots ``holding`` (rotations (n, 3, 3), origins (n, 3), zeros for the others), the
    bodies of those robots and one more slot for the cargo (masses, centres, inertias), i's grasp
    frame (R_bg, p_bg) and the cargo frame's origin p_bc. Cargo frame C in B_i:
    R_bc = R_bg R_ch^T, p_bc = p_bg - R_bc p_ch (handrail j's pose (R_ch, p_ch) in C); base j in
    C: R_cb = R_chj R_bgj^T, p_cb = p_chj - R_cb p_bgj; base j in B_i:
    (R_bc R_cb, p_bc + R_bc p_cb)."""
    models = [robot_body(team, m, q) for m in range(len(team.parent))]
    _, _, _, rot_bg, pos_bg = models[team.model_of[i]]
    rot_bc = rot_bg @ handrail_rot[i].T
    pos_bc = pos_bg - rot_bc @ handrail_pos[i]
    n, count = len(handrail_rot), len(holding) + 1
    rot_base, pos_base = np.zeros((n, 3, 3)), np.zeros((n, 3))
    masses, coms, inertias = np.zeros(count), np.zeros((count, 3)), np.zeros((count, 3, 3))
    for idx in range(len(holding)):
        j = holding[idx]
        mass, com, inertia, rot_bgj, pos_bgj = models[team.model_of[j]]
        rot_cb = handrail_rot[j] @ rot_bgj.T
        pos_cb = handrail_pos[j] - rot_cb @ pos_bgj
        rot_base[j] = rot_bc @ rot_cb
        pos_base[j] = pos_bc + rot_bc @ pos_cb
        masses[idx] = mass
        coms[idx], inertias[idx] = place_body(com, inertia, rot_base[j], pos_base[j])
    return rot_base, pos_base, (masses, coms, inertias), rot_bg, pos_bg, pos_bc


@njit(cache=True)
def _observation_actions(
    team: TeamModel,
    handrail_rot: np.ndarray,
    handrail_pos: np.ndarray,
    gains: np.ndarray,
    arm_scale_rad: float,
    acting: np.ndarray,
    holding: np.ndarray,
    obs: BaseTracking,
    with_cargo: bool,
) -> np.ndarray:
    """Actions (k, 8) of the acting robots (all holding the cargo): thrust u / thrust_limit,
    tilt offset 0, pan offset clip(ref_pan / arm_scale_rad, -1, 1). Each robot's thrust u is its
    share of the team wrench worked out in its own base frame, where the cargo is at rest (v = 0)
    and the reference errors are the base's (the grasp is rigid): e_p = -base_pos_err,
    v_ref = -base_vel_err, e_R = -base_att_err, and the reference acceleration of the cargo
    origin seen from the base a_ref = ref_acc + w'_ref x r + w_ref x (w_ref x r),
    r = -ref_pos_rel."""
    out = np.zeros((len(acting), 8))
    for a in range(len(acting)):
        i = acting[a]
        rot_base, pos_base, bodies, rot_bg, pos_bg, pos_bc = _team_in_base(
            team, handrail_rot, handrail_pos, i, holding, obs.joint_pos[a]
        )
        if with_cargo:
            mass, com, inertia = body_from_params(obs.cargo_params[a])
            masses, coms, inertias = bodies
            masses[-1] = mass
            coms[-1], inertias[-1] = place_body(com, inertia, rot_bg, pos_bg)
        w_ref, wd_ref, r = obs.ref_ang_vel[a], obs.ref_ang_acc[a], -obs.ref_pos_rel[a]
        acc_ref = obs.ref_acc[a] + np.cross(wd_ref, r) + np.cross(w_ref, np.cross(w_ref, r))
        w = obs.base_ang_vel[a]
        acc, wd = pd_accelerations(
            gains, -obs.base_pos_err[a], -obs.base_vel_err[a], -obs.base_att_err[a],
            w_ref - w, acc_ref, wd_ref,
        )  # fmt: skip
        commands, _ = thrust_commands(team, holding, rot_base, pos_base, bodies, pos_bc, w, acc, wd)
        out[a, :6] = commands[i] / team.thrust_limit[i]
        out[a, 7] = min(max(obs.ref_pan[a, 0] / arm_scale_rad, -1.0), 1.0)
    return out


class ObservationController:
    """The cooperative controller driven by the env's observations only, scored like a policy.

    Each robot works out the team's wrench from its own observation, in its own base frame: its
    base tracking errors stand for the cargo's (the grasp is rigid), the cargo and the other
    robots are placed by the known grasp geometry (handrail poses on the cargo; peers' arms
    assumed at this robot's own angles, since all follow the same pan ramp), and the cargo's
    inertia comes from ``cargo_model``: "estimate" (this robot's own live estimate, from the
    observation, in its grasp frame), "none" (no cargo), or "truth" (``truth_params``, cargo
    frame, for comparison only). It then applies its share of the allocation (the equations of
    ``CooperativeController``) and sends the arm targets of the reference pan ramp.

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

    @classmethod
    def for_env(cls, env, cargo_model: str = "estimate") -> ObservationController:
        """Build from an ``AstrobeeCargoEnv`` (geometry; the truth only for "truth")."""
        sim = env.sim
        truth = sim.world.cargo_params() if cargo_model == "truth" else None
        return cls(
            sim.robots,
            sim.handrail_pose,
            sim.obs_layout,
            cargo_model,
            truth,
            agents=list(env.possible_agents),
        )

    def _tracking(self, acting: np.ndarray, obs: np.ndarray) -> BaseTracking:
        """The blocks of the observations ``obs`` (k, obs_dim) of the robots ``acting``."""
        lay = self.layout
        if self.cargo_model == "estimate":
            params = obs[:, lay["estimate_mean"]]
        else:
            params = self._truth_in_grasp[acting]
        blocks = [obs[:, lay[name]] for name in BaseTracking._fields[:-1]]
        return BaseTracking(*(np.ascontiguousarray(b) for b in (*blocks, params)))

    def _actions(self, acting: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """Actions (k, 8) of the robots ``acting`` (all holding the cargo) from their
        observations (k, obs_dim) (``_observation_actions``)."""
        return _observation_actions(
            self.team.team,
            self._handrail_rot,
            self._handrail_pos,
            self.team._gains,
            self.arm_scale,
            acting,
            np.sort(acting),
            self._tracking(acting, obs),
            self.cargo_model != "none",
        )

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        """SB3's signature: returns (actions, state)."""
        del episode_start, deterministic
        if isinstance(observation, dict):
            unknown = [a for a in observation if a not in self.robot_index]
            if unknown:
                raise ValueError(f"unknown agents {unknown}; agents: {list(self.robot_index)}")
            acting = np.array([self.robot_index[a] for a in observation], dtype=np.int64)
            obs = np.stack([np.asarray(o, dtype=float) for o in observation.values()])
            actions = self._actions(acting, obs)
            return dict(zip(observation, actions, strict=True)), state
        obs = np.asarray(observation, dtype=float)
        if obs.ndim != 2 or obs.shape[0] != len(self.robots):
            raise ValueError(
                f"observation must be a dict or an array ({len(self.robots)}, obs_dim), "
                f"got shape {obs.shape}"
            )
        return self._actions(np.arange(len(self.robots), dtype=np.int64), obs), state
