"""Cooperative controller: all robots together track the cargo reference.

The robots and the cargo are treated as one rigid body (the arms move slowly; their own motion
is a disturbance the feedback absorbs). With the composite mass M, centre of mass c and inertia
I_c (robots known, cargo from live estimates, the truth, or nothing), a PD law with feed-forward
gives the desired acceleration of the cargo frame (Astrobee's law, facts file section 3.1:
F = m (a_ref + Kd (v_ref - v) + Kp e_p), and likewise for attitude), hence the total wrench about
c (world axes):
    F = M (a + wd x (c - p) + w x (w x (c - p))),     tau = I_c wd + w x I_c w.
The wrench is allocated among the robots through the grasp geometry by the minimum-norm solution
weighted by each robot's propulsion limits, then scaled down uniformly if any robot saturates (so
the direction of the total wrench is kept). A robot that has let go of the cargo (its state None)
is part of neither the composite body nor the allocation: the robots still holding share the
whole wrench.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from astrocargo.estimator.inertia import (
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    transform_params,
)
from astrocargo.estimator.rne import RobotDescription, grasp_pose, link_poses, wrench_transform

from .trajectories import Reference

# Translation: ISS flight-mode gains (iss.config); attitude: gnc.config defaults, which the
# heavier robot-cargo assembly can follow within the propulsion limits (facts section 3.2).
POS_KP, POS_KD = 0.6, 1.2
ATT_KP, ATT_KD = 2.0, 1.6
CARGO_MODELS = ("estimate", "none", "truth")


def rotation_log(rot: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix."""
    cos = np.clip((np.trace(rot) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    v = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    if np.pi - angle < 1e-6:
        w, vecs = np.linalg.eigh(0.5 * (rot + rot.T))
        return angle * vecs[:, -1]
    return angle / (2 * np.sin(angle)) * v


@dataclass(frozen=True)
class RobotState:
    """One robot's base pose and twist (world axes) and arm joint angles."""

    rot: np.ndarray
    pos: np.ndarray
    joint_pos: np.ndarray


@dataclass(frozen=True)
class CargoState:
    """The cargo frame's pose and twist in world axes."""

    rot: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    w: np.ndarray


class CooperativeController:
    """Computes every robot's thrust command and arm targets.

    Args:
        robots: the robots' known models.
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
        self._link_params: dict[int, np.ndarray] = {}

    def _robot_params_world(self, robot: RobotDescription, state: RobotState) -> np.ndarray:
        """The robot's standard parameters (all links) in the world frame."""
        key = id(robot)
        if key not in self._link_params:
            self._link_params[key] = np.stack(
                [params_from_mass_com_inertia(k.mass, k.com, k.inertia_com) for k in robot.links]
            )
        rots, poss = link_poses(robot, state.joint_pos)
        return transform_params(
            self._link_params[key], state.rot @ rots, state.pos + poss @ state.rot.T
        ).sum(axis=0)

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
        or None for no model.
        """
        if len(robot_states) != len(self.robots):
            raise ValueError(
                f"robot_states must hold one entry per robot ({len(self.robots)}), "
                f"got {len(robot_states)}"
            )
        holding = [i for i, st in enumerate(robot_states) if st is not None]
        if not holding:
            raise ValueError("no robot holds the cargo: every robot state is None")
        kp, kd, akp, akd = self.gains
        total = sum(
            (self._robot_params_world(self.robots[i], robot_states[i]) for i in holding),
            np.zeros(10),
        )
        if cargo_params is not None:
            total = total + transform_params(cargo_params, cargo.rot, cargo.pos)
        mass, com, inertia = mass_com_inertia_from_params(total)
        acc = ref.acc + kd * (ref.vel - cargo.vel) + kp * (ref.pos - cargo.pos)
        e_rot = rotation_log(ref.rot @ cargo.rot.T)
        wd = ref.wd + akd * (ref.w - cargo.w) + akp * e_rot
        r = com - cargo.pos
        w = cargo.w
        force = mass * (acc + np.cross(wd, r) + np.cross(w, np.cross(w, r)))
        torque = inertia @ wd + np.cross(w, inertia @ w)
        wrench = np.concatenate((force, torque))
        # Allocation: sum_i G_i u_i = wrench, G_i maps robot i's body wrench to world about com.
        gs = [wrench_transform(robot_states[i].rot, robot_states[i].pos - com) for i in holding]
        limits = [self.robots[i].thrust_limit for i in holding]
        weight = [np.diag(lim**2) for lim in limits]
        mat = sum(g @ wgt @ g.T for g, wgt in zip(gs, weight, strict=True))
        lam = np.linalg.solve(mat, wrench)
        cmds = [wgt @ g.T @ lam for g, wgt in zip(gs, weight, strict=True)]
        ratio = max(float(np.max(np.abs(u) / lim)) for u, lim in zip(cmds, limits, strict=True))
        scale = 1.0 / ratio if ratio > 1.0 else 1.0
        self.last_ratio = ratio
        out = [np.zeros(6) for _ in self.robots]
        for i, u in zip(holding, cmds, strict=True):
            out[i] = scale * u
        return out


def _exp_rotvec(v: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


class ObservationController:
    """The cooperative controller driven by the env's observations only, scored like a policy.

    Each robot works out the team's wrench from its own observation, in its own base frame: its
    base tracking errors stand for the cargo's (the grasp is rigid), the cargo and the other
    robots are placed by the known grasp geometry (handrail poses on the cargo; peers' arms
    assumed at this robot's own angles, since all follow the same pan ramp), and the cargo's
    inertia comes from ``cargo_model``: "estimate" (this robot's own live estimate, from the
    observation), "none" (no cargo), or "truth" (``truth_params``, for comparison only). It then
    applies its share of the allocation (``CooperativeController``) and sends the arm targets of
    the reference pan ramp.

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
        self.handrail_poses = [(np.asarray(r), np.asarray(p)) for r, p in handrail_poses]
        self.layout = layout
        self.cargo_model = cargo_model
        self.truth_params = None if truth_params is None else np.asarray(truth_params, float)
        self.arm_scale = float(arm_offset_scale_rad)
        self.team = CooperativeController(self.robots)
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

    def _act_one(self, i: int, o: np.ndarray, holding: list[int]) -> np.ndarray:
        lay = self.layout
        q = o[lay["joint_pos"]]
        # Cargo frame in this robot's base frame, through its grasp and the handrail it holds.
        rot_bg, pos_bg = grasp_pose(self.robots[i], q)
        rot_ch, pos_ch = self.handrail_poses[i]
        rot_bc = rot_bg @ rot_ch.T
        pos_bc = pos_bg - rot_bc @ pos_ch
        # Other robots' bases in this base frame (their arms assumed at this robot's angles).
        states: list[RobotState | None] = []
        for j, robot in enumerate(self.robots):
            if j not in holding:
                states.append(None)
                continue
            rot_bgj, pos_bgj = grasp_pose(robot, q)
            rot_chj, pos_chj = self.handrail_poses[j]
            rot_cb = rot_chj @ rot_bgj.T
            pos_cb = pos_chj - rot_cb @ pos_bgj
            states.append(RobotState(rot_bc @ rot_cb, pos_bc + rot_bc @ pos_cb, q))
        # Tracking errors of the base stand for the cargo's (rigid assembly).
        e_rot = o[lay["base_att_err"]]
        w = o[lay["base_ang_vel"]]
        ref_w = o[lay["ref_ang_vel"]]
        ref_wd = o[lay["ref_ang_acc"]]
        rel = -o[lay["ref_pos_rel"]]  # base minus cargo reference, base frame
        ref_acc_base = (
            o[lay["ref_acc"]] + np.cross(ref_wd, rel) + np.cross(ref_w, np.cross(ref_w, rel))
        )
        cargo = CargoState(rot_bc, pos_bc, np.zeros(3), w)
        # A reference whose errors relative to `cargo` are the base's: position and velocity
        # (the cargo moves with the base), attitude (R_ref = R exp(-e) in base axes).
        ref = Reference(
            pos=pos_bc - o[lay["base_pos_err"]],
            vel=-o[lay["base_vel_err"]],
            acc=ref_acc_base,
            rot=_exp_rotvec(-e_rot) @ rot_bc,
            w=ref_w,
            wd=ref_wd,
            pan=float(o[lay["ref_pan"]][0]),
            pan_rate=float(o[lay["ref_pan"]][1]),
        )
        params = None
        if self.cargo_model == "truth":
            params = self.truth_params
        elif self.cargo_model == "estimate":
            # Own estimate is in this robot's grasp frame; the cargo frame is (rot_ch, pos_ch)^-1.
            params = transform_params(o[lay["estimate_mean"]], rot_ch, pos_ch)
        thrust = self.team.commands(ref, cargo, states, params)[i]
        action = np.zeros(8)
        action[:6] = thrust / self.robots[i].thrust_limit
        action[7] = np.clip(ref.pan / self.arm_scale, -1.0, 1.0)
        return action

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        """SB3's signature: returns (actions, state)."""
        del episode_start, deterministic
        if isinstance(observation, dict):
            unknown = [a for a in observation if a not in self.robot_index]
            if unknown:
                raise ValueError(f"unknown agents {unknown}; agents: {list(self.robot_index)}")
            holding = sorted(self.robot_index[a] for a in observation)
            acts = {
                a: self._act_one(self.robot_index[a], np.asarray(o), holding)
                for a, o in observation.items()
            }
            return acts, state
        obs = np.asarray(observation, dtype=float)
        if obs.ndim != 2 or obs.shape[0] != len(self.robots):
            raise ValueError(
                f"observation must be a dict or an array ({len(self.robots)}, obs_dim), "
                f"got shape {obs.shape}"
            )
        holding = list(range(len(self.robots)))
        return np.stack([self._act_one(i, o, holding) for i, o in enumerate(obs)]), state
