"""From the agents' actions to the robots' commands (the env docstring's Action Space section):
each acting robot's action a (8,) is clipped to [-1, 1]; a[:6] scales the thrust limits to the
commanded propulsion wrench u = a[:6] * u_max (N, N m, base frame); a[6:] asks for the servo
targets q_want = q_deployed + ARM_OFFSET_RAD a[6:] (tilt, pan, rad), which the targets approach
at the servos' speed limit: q' = clip(q + clip(q_want - q, -dq, dq), q_low, q_high) with
dq = ARM_SPEED_RADPS dt.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from astrocargo.envs.world import ARM_DEPLOYED_RAD

ACTION_DIM = 8
ARM_DEPLOYED = np.asarray(ARM_DEPLOYED_RAD, dtype=float)
ARM_OFFSET_RAD = 0.5  # reach of the arm actions around the deployed pose
ARM_SPEED_RADPS = 0.12  # URDF joint velocity limit (sources §5, docs/design.md)


@njit(cache=True)
def first_non_finite(actions, acting):
    """The first acting robot (bool (N,)) whose action row is not all finite, or -1."""
    for i in range(actions.shape[0]):
        if acting[i] and not np.isfinite(actions[i]).all():
            return i
    return -1


@njit(cache=True)
def scale_actions_into(clipped, n_clipped, effort, commands, targets, actions, acting,
                       thrust_limits, arm_targets, joint_low, joint_high, max_move_rad,
                       deployed_rad, offset_rad):  # fmt: skip
    """``scale_actions``' results written into its first five arguments (``targets`` must not
    be ``arm_targets``)."""
    n = actions.shape[0]
    clipped[:], n_clipped[:], effort[:] = 0.0, 0, 0.0
    for i in range(n):
        if not acting[i]:
            continue
        for j in range(8):
            clipped[i, j] = min(max(actions[i, j], -1.0), 1.0)
            n_clipped[i] += clipped[i, j] != actions[i, j]
            effort[i] += clipped[i, j] ** 2
    for i in range(n):
        for j in range(commands.shape[1]):
            commands[i, j] = clipped[i, j] * thrust_limits[i, j]
        for j in range(arm_targets.shape[1]):
            wanted = deployed_rad[j] + offset_rad * clipped[i, 6 + j]
            move = min(max(wanted - arm_targets[i, j], -max_move_rad), max_move_rad)
            targets[i, j] = min(max(arm_targets[i, j] + move, joint_low[i, j]), joint_high[i, j])


@njit(cache=True)
def scale_actions(actions, acting, thrust_limits, arm_targets, joint_low, joint_high,
                  max_move_rad, deployed_rad, offset_rad):  # fmt: skip
    """The module docstring's map for every robot: the clipped actions (N, 8) (zeros for robots
    not ``acting``), how many entries each robot had clipped (N,), the effort sum(a^2) (N,),
    the thrust commands (N, 6) and the new servo targets (N, 2) (every robot's, the others'
    approaching the deployed pose)."""
    n = actions.shape[0]
    clipped, n_clipped, effort = np.zeros((n, 8)), np.zeros(n, dtype=np.int64), np.zeros(n)
    commands, targets = np.empty((n, 6)), np.empty_like(arm_targets)
    scale_actions_into(
        clipped, n_clipped, effort, commands, targets, actions, acting, thrust_limits,
        arm_targets, joint_low, joint_high, max_move_rad, deployed_rad, offset_rad,
    )  # fmt: skip
    return clipped, n_clipped, effort, commands, targets


@njit(cache=True)
def thrust_saturation_into(out, actions, clipped):
    """``thrust_saturation`` written into ``out`` (N,)."""
    for i in range(actions.shape[0]):
        wanted, delivered = 0.0, 0.0
        for j in range(6):
            wanted += actions[i, j] ** 2
            delivered += clipped[i, j] ** 2
        out[i] = 0.0
        if wanted > 0:
            out[i] = 1.0 - np.sqrt(delivered) / np.sqrt(wanted)


@njit(cache=True)
def thrust_saturation(actions: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """Per row, the share of the requested thrust a robot could not deliver: 1 - |a_c| / |a|
    over the six thrust entries of the action a as given and a_c as clipped to [-1, 1] (0 for
    a zero request), in [0, 1]."""
    out = np.empty(actions.shape[0])
    thrust_saturation_into(out, actions, clipped)
    return out


@njit(cache=True)
def command_period(actions, acting, thrust_limits, joint_low, joint_high, max_move_rad, dt_s,
                   arm_targets, arm_rates, normals, actuation_std, thrust_scale, rows, thrust_ctrl,
                   arm_ctrl, ctrl, n_clipped, effort, saturation, commands):  # fmt: skip
    """One period's commands, in place: ``scale_actions`` for every robot (servo targets
    ``arm_targets`` (N, 2) and their rate ``arm_rates`` = (q' - q) / dt, effort sum(a^2) and clipped
    entries (N,), ``thrust_saturation`` (N,), zero for robots not ``acting``) and the thrust
    commands ``commands`` (N, 6). MuJoCo's controls ``ctrl`` of the robots in the world
    (``rows``, (H,) robot indices; ``thrust_ctrl`` (H, 6), ``arm_ctrl`` (H, 2) actuator ids) get
    the delivered wrench u_d = s (u + (std_abs + std_rel |u|) n) with the standard normals n:
    ``normals``' first 6 H as (H, 6); ``actuation_std`` rows (std_abs, std_rel) and the thrust
    scale s (H,) of faults, and the servo targets."""
    n = actions.shape[0]
    clipped, targets = np.empty((n, 8)), np.empty_like(arm_targets)
    scale_actions_into(
        clipped, n_clipped, effort, commands, targets, actions, acting, thrust_limits,
        arm_targets, joint_low, joint_high, max_move_rad, ARM_DEPLOYED, ARM_OFFSET_RAD,
    )  # fmt: skip
    thrust_saturation_into(saturation, actions, clipped)
    for i in range(n):
        if not acting[i]:
            saturation[i] = 0.0
        for j in range(arm_targets.shape[1]):
            arm_rates[i, j] = (targets[i, j] - arm_targets[i, j]) / dt_s
            arm_targets[i, j] = targets[i, j]
    std_abs, std_rel = actuation_std[0], actuation_std[1]
    for k in range(rows.shape[0]):
        u = commands[rows[k]]
        for j in range(thrust_ctrl.shape[1]):
            noise = normals[6 * k + j]
            std = std_abs[j] + std_rel[j] * abs(u[j])
            ctrl[thrust_ctrl[k, j]] = (u[j] + std * noise) * thrust_scale[k]
        for j in range(arm_ctrl.shape[1]):
            ctrl[arm_ctrl[k, j]] = arm_targets[rows[k], j]
