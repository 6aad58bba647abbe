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
the direction of the total wrench is kept).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from astrocargo.estimator.inertia import (
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    transform_params,
)
from astrocargo.estimator.rne import RobotDescription, propagate, wrench_transform

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

    def _robot_params_world(self, robot: RobotDescription, state: RobotState) -> np.ndarray:
        nj = robot.n_joints
        zeros = np.zeros(3)
        kin = propagate(robot, zeros, zeros, zeros, state.joint_pos, np.zeros(nj), np.zeros(nj))
        total = np.zeros(10)
        for k, link in enumerate(robot.links):
            pi_link = params_from_mass_com_inertia(link.mass, link.com, link.inertia_com)
            rot = state.rot @ kin.rot[k]
            pos = state.pos + state.rot @ kin.pos[k]
            total = total + transform_params(pi_link, rot, pos)
        return total

    def commands(
        self,
        ref: Reference,
        cargo: CargoState,
        robot_states: list[RobotState],
        cargo_params: np.ndarray | None,
    ) -> list[np.ndarray]:
        """Thrust commands (6,) per robot, [force N; torque N m] in each base frame.

        ``cargo_params``: the cargo's standard parameters in the cargo frame, or None for no model.
        """
        kp, kd, akp, akd = self.gains
        total = sum(
            (
                self._robot_params_world(r, s)
                for r, s in zip(self.robots, robot_states, strict=True)
            ),
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
        gs = [wrench_transform(s.rot, s.pos - com) for s in robot_states]
        limits = [r.thrust_limit for r in self.robots]
        weight = [np.diag(lim**2) for lim in limits]
        mat = sum(g @ wgt @ g.T for g, wgt in zip(gs, weight, strict=True))
        lam = np.linalg.solve(mat, wrench)
        cmds = [wgt @ g.T @ lam for g, wgt in zip(gs, weight, strict=True)]
        ratio = max(float(np.max(np.abs(u) / lim)) for u, lim in zip(cmds, limits, strict=True))
        scale = 1.0 / ratio if ratio > 1.0 else 1.0
        self.last_ratio = ratio
        return [scale * u for u in cmds]
