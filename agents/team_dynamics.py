"""The team as one rigid body: composite inertia, desired wrench and its allocation, compiled.

The cooperative controllers (``controllers.py``) treat the robots and the cargo as one body whose
arms move (section "moving arms" below: the composite body at the arms' current angles, plus the
wrench of the links' motion relative to the cargo from the joint rates). Every function
here works in one frame W (the world, or one robot's base frame: the equations are the same), with
vectors in metres, seconds, radians, kilograms, and wrenches [force (N); moment (N m)].

Kinematics of robot j's arm (links k = 1..L-1, parent p, joint angle q_k, unit axis e_k):
    R_k = R_p R_pk0 exp(e_k q_k),    p_k = p_p + R_p p_pk      (link frames in its base)
(``arm_kinematics``, with the arms' motion relative to their grasp frames).

Composite body of bodies b (robot links and the cargo), mass m_b, centre c_b and inertia I_b about
c_b (W axes), by the parallel-axis theorem:
    M = sum m_b,   c = sum m_b c_b / M,  I_c = sum I_b + m_b (|r_b|^2 1 - r_b r_b^T), r_b = c_b - c

Desired motion of the cargo frame (PD with feed-forward, Astrobee's law, sources §3.1):
    a  = a_ref  + K_d (v_ref - v) + K_p e_p,      e_p = p_ref - p
    w' = w'_ref + K_dw (w_ref - w) + K_pw e_R,    e_R = log(R_ref R^T)
and the wrench about c that gives it to the composite body, with r = c - p:
    F = M (a + w' x r + w x (w x r)),      tau = I_c w' + w x I_c w.

Allocation: robot j's body wrench u_j (about its base origin, base axes) acts in W about c as
G_j u_j, G_j = [[R_j, 0], [[p_j - c]x R_j, R_j]]. The minimum of sum_j u_j^T W_j^-1 u_j subject
to sum_j G_j u_j = [F; tau], with W_j = diag(thrust_limit_j^2), is
    u_j = W_j G_j^T lambda,    (sum_j G_j W_j G_j^T) lambda = [F; tau]
then every u_j is scaled by 1 / max(1, ratio), ratio = max_j,k |u_jk| / thrust_limit_jk, so a
saturating team keeps the direction of its total wrench.

Each function is compiled with numba (``@njit(cache=True)``) and takes the robots' models as one
``TeamModel`` of arrays (``team_model``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import (
    cross3,
    cross3_into,
    matmul3,
    matmul3_into,
    matvec3,
    matvec3_into,
    skew_into,
)
from astrocargo.estimator.rne import RobotDescription

from .arm_kinematics import (
    ARM_STEP_S as ARM_STEP_S,  # the central differences' step, read by the tests
)
from .arm_kinematics import (
    arm_motion_into,
    arm_work,
    empty_arm_motions,
    link_frames,
)


class TeamModel(NamedTuple):
    """The robots' known models as arrays: the distinct robot models (m of them, L links each,
    base first; robots with equal models share one, so a team of one kind costs one forward
    kinematics per arm pose) and, per robot (n), its model and thrust limits."""

    parent: np.ndarray  # (m, L) int64, parent link of each link (unused for the base)
    rot_in_parent: np.ndarray  # (m, L, 3, 3) link frame at q = 0 in its parent's frame
    pos_in_parent: np.ndarray  # (m, L, 3) m, link origin in its parent's frame
    joint_axis: np.ndarray  # (m, L, 3) unit joint axis in the link frame (zeros for the base)
    link_mass: np.ndarray  # (m, L) kg
    link_com: np.ndarray  # (m, L, 3) m, centre of mass in the link frame
    link_inertia: np.ndarray  # (m, L, 3, 3) kg m^2 about the centre of mass, link axes
    grasp_link: np.ndarray  # (m,) int64, the link the grasp frame is fixed to
    grasp_rot: np.ndarray  # (m, 3, 3) grasp frame in that link's frame
    grasp_pos: np.ndarray  # (m, 3) m
    model_of: np.ndarray  # (n,) int64, each robot's model
    thrust_limit: np.ndarray  # (n, 6) N, N m: body force and torque limits


def _model_arrays(robot: RobotDescription) -> tuple:
    """One robot's model as the arrays of a ``TeamModel`` row (fields up to grasp_pos)."""
    links = robot.links
    return (
        np.array([max(k.parent, 0) for k in links], dtype=np.int64),
        np.array([k.rot_in_parent for k in links], dtype=float),
        np.array([k.pos_in_parent for k in links], dtype=float),
        np.array([np.zeros(3) if k.joint_axis is None else k.joint_axis for k in links], float),
        np.array([k.mass for k in links], dtype=float),
        np.array([k.com for k in links], dtype=float),
        np.array([k.inertia_com for k in links], dtype=float),
        np.int64(robot.grasp_link),
        np.asarray(robot.grasp_rot, dtype=float),
        np.asarray(robot.grasp_pos, dtype=float),
    )


def team_model(robots: list[RobotDescription]) -> TeamModel:
    """Stack the robots' models. They must share one arm structure (the same number of links)."""
    if not robots:
        raise ValueError("team_model needs at least one robot")
    n_links = {len(r.links) for r in robots}
    if len(n_links) != 1:
        raise ValueError(f"robots must all have the same number of links, got {sorted(n_links)}")
    models: list[tuple] = []
    model_of = []
    for robot in robots:
        arrays = _model_arrays(robot)
        same = [all(np.array_equal(a, b) for a, b in zip(arrays, m, strict=True)) for m in models]
        if True not in same:
            models.append(arrays)
        model_of.append(same.index(True) if True in same else len(models) - 1)
    fields = [np.ascontiguousarray(np.stack(column)) for column in zip(*models, strict=True)]
    return TeamModel(
        *fields,
        model_of=np.array(model_of, dtype=np.int64),
        thrust_limit=np.ascontiguousarray([r.thrust_limit for r in robots], dtype=float),
    )


@njit(cache=True)
def composite_body(
    masses: np.ndarray, coms: np.ndarray, inertias: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and inertia about it of rigidly joined bodies (b,), (b, 3),
    (b, 3, 3) (each about its own centre), by the parallel-axis theorem."""
    mass = masses.sum()
    com = np.zeros(3)
    for b in range(len(masses)):
        for i in range(3):
            com[i] += masses[b] * coms[b, i]
    com /= mass
    inertia, r = np.zeros((3, 3)), np.empty(3)
    for b in range(len(masses)):
        for i in range(3):
            r[i] = coms[b, i] - com[i]
        r_sq = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        for i in range(3):
            for j in range(3):
                shift = (r_sq if i == j else 0.0) - r[i] * r[j]
                inertia[i, j] += inertias[b, i, j] + masses[b] * shift
    return mass, com, inertia


@njit(cache=True)
def robot_body(team: TeamModel, m: int, q: np.ndarray) -> tuple:
    """A robot of model m at joint angles q, in its base frame: the composite body of its links
    (mass kg, centre m, inertia about it kg m^2) and its grasp frame (rotation, origin m)."""
    return body_of_frames(team, m, *link_frames(team, m, q))


@njit(cache=True)
def body_of_frames(team: TeamModel, m: int, rots: np.ndarray, poss: np.ndarray) -> tuple:
    """``robot_body`` from model m's link frames in its base (``link_frames``)."""
    n_links = len(rots)
    coms, inertias, rotated = np.empty((n_links, 3)), np.empty((n_links, 3, 3)), np.empty((3, 3))
    for k in range(n_links):  # each link's centre R_k c_k + p_k and inertia R_k I_k R_k^T
        matvec3_into(coms[k], rots[k], team.link_com[m, k])
        coms[k] += poss[k]
        matmul3_into(rotated, rots[k], team.link_inertia[m, k])
        matmul3_into(inertias[k], rotated, rots[k].T)
    mass, com, inertia = composite_body(team.link_mass[m], coms, inertias)
    g = team.grasp_link[m]
    rot_grasp = matmul3(rots[g], team.grasp_rot[m])
    pos_grasp = poss[g] + matvec3(rots[g], team.grasp_pos[m])
    return mass, com, inertia, rot_grasp, pos_grasp


@njit(cache=True)
def place_body(
    com: np.ndarray, inertia: np.ndarray, rot: np.ndarray, pos: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass and inertia about it of a body given in frame A, expressed in W, A's pose
    in W being (rot, pos): c_W = R c + p, I_W = R I R^T."""
    com_w, inertia_w = np.empty(3), np.empty((3, 3))
    place_body_into(com_w, inertia_w, com, inertia, rot, pos, np.empty((3, 3)))
    return com_w, inertia_w


@njit(cache=True)
def place_body_into(
    com_w: np.ndarray,
    inertia_w: np.ndarray,
    com: np.ndarray,
    inertia: np.ndarray,
    rot: np.ndarray,
    pos: np.ndarray,
    scratch: np.ndarray,
) -> None:
    """com_w (3,), inertia_w (3, 3) = ``place_body`` (scratch: (3, 3))."""
    matvec3_into(com_w, rot, com)
    for i in range(3):
        com_w[i] += pos[i]
    matmul3_into(scratch, rot, inertia)
    matmul3_into(inertia_w, scratch, rot.T)


@njit(cache=True)
def body_from_params(params: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (m) and inertia about it (kg m^2) of the standard parameters
    pi = [m, m c, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (I about the origin), in pi's frame:
    c = h / m, I_c = I_o - m (|c|^2 1 - c c^T)."""
    mass = params[0]
    com = params[1:4] / mass
    xx, yy, zz, xy, xz, yz = params[4:10]
    inertia = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])  # I_o, then I_c
    com_sq = com[0] * com[0] + com[1] * com[1] + com[2] * com[2]
    for i in range(3):
        for j in range(3):
            inertia[i, j] -= mass * ((com_sq if i == j else 0.0) - com[i] * com[j])
    return mass, com, inertia


@njit(cache=True)
def pd_accelerations(
    gains: np.ndarray,
    pos_err: np.ndarray,
    vel_err: np.ndarray,
    rot_err: np.ndarray,
    w_err: np.ndarray,
    acc_ref: np.ndarray,
    wd_ref: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Desired linear (m/s^2) and angular (rad/s^2) accelerations of the cargo frame, gains
    (K_p, K_d, K_pw, K_dw) in 1/s^2, 1/s: a = a_ref + K_d v_err + K_p p_err and
    w' = w'_ref + K_dw w_err + K_pw e_R (errors are reference minus state)."""
    kp, kd, akp, akd = gains[0], gains[1], gains[2], gains[3]
    acc = acc_ref + kd * vel_err + kp * pos_err
    wd = wd_ref + akd * w_err + akp * rot_err
    return acc, wd


@njit(cache=True)
def team_wrench(
    mass: float,
    com: np.ndarray,
    inertia: np.ndarray,
    origin: np.ndarray,
    w: np.ndarray,
    acc: np.ndarray,
    wd: np.ndarray,
) -> np.ndarray:
    """Wrench (6,) about the centre of mass ``com`` that gives the composite body the cargo
    frame's desired acceleration ``acc`` of its origin ``origin`` and angular acceleration ``wd``
    at angular velocity ``w``: F = M (a + w' x r + w x (w x r)), r = com - origin,
    tau = I_c w' + w x I_c w."""
    r = com - origin
    out = np.empty(6)
    out[:3] = mass * (acc + cross3(wd, r) + cross3(w, cross3(w, r)))  # F
    out[3:] = matvec3(inertia, wd) + cross3(w, matvec3(inertia, w))  # tau
    return out


@njit(cache=True)
def wrench_map(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """G (6, 6): a wrench [f; n about A's origin] in frame A to W about W's origin, A's pose in W
    being (rot, pos): f_W = R f, n_W = R n + pos x (R f)."""
    g = np.zeros((6, 6))
    wrench_map_into(g, rot, pos, np.empty((3, 3)))
    return g


@njit(cache=True)
def wrench_map_into(g: np.ndarray, rot: np.ndarray, pos: np.ndarray, scratch: np.ndarray) -> None:
    """g (6, 6) = ``wrench_map`` (scratch: (3, 3))."""
    skew_into(scratch, pos)
    for i in range(3):
        for j in range(3):
            g[i, j] = g[i + 3, j + 3] = rot[i, j]
            g[i, j + 3] = 0.0
    matmul3_into(g[3:, :3], scratch, rot)


@njit(cache=True)
def allocate(
    team: TeamModel,
    holding: np.ndarray,
    rot_base: np.ndarray,
    pos_base: np.ndarray,
    com: np.ndarray,
    wrench: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Body wrenches (n, 6) of the robots (zeros for those not ``holding``) summing to ``wrench``
    about ``com``: weighted minimum norm u_j = W_j G_j^T lambda, (sum G W G^T) lambda = wrench,
    W_j = diag(limit_j^2), scaled down together if any exceeds its limit. Also returns the
    largest |u_jk| / limit_jk before scaling."""
    maps, normal = np.empty((len(holding), 6, 6)), np.zeros((6, 6))
    weight, lever, scratch = np.empty(6), np.empty(3), np.empty((3, 3))
    for idx in range(len(holding)):
        j, g = holding[idx], maps[idx]
        for i in range(3):
            lever[i] = pos_base[j, i] - com[i]
        wrench_map_into(g, rot_base[j], lever, scratch)
        for k in range(6):
            weight[k] = team.thrust_limit[j, k] ** 2
        for r in range(6):  # normal += G_j W_j G_j^T, summed in loops (6x6: no BLAS call)
            for c in range(6):
                term = 0.0
                for k in range(6):
                    term += g[r, k] * weight[k] * g[c, k]
                normal[r, c] += term
    lam = np.linalg.solve(normal, wrench)
    commands = np.zeros((len(rot_base), 6))
    ratio = 0.0
    for idx in range(len(holding)):
        j = holding[idx]
        for k in range(6):  # u_j = W_j G_j^T lambda
            g_lam = 0.0
            for r in range(6):
                g_lam += maps[idx, r, k] * lam[r]
            commands[j, k] = team.thrust_limit[j, k] ** 2 * g_lam
            ratio = max(ratio, abs(commands[j, k]) / team.thrust_limit[j, k])
    if ratio > 1.0:
        commands /= ratio
    return commands, ratio


@njit(cache=True)
def thrust_commands(
    team: TeamModel,
    holding: np.ndarray,
    rot_base: np.ndarray,
    pos_base: np.ndarray,
    bodies: tuple[np.ndarray, np.ndarray, np.ndarray],
    origin: np.ndarray,
    w: np.ndarray,
    acc: np.ndarray,
    wd: np.ndarray,
) -> tuple[np.ndarray, float]:
    """The robots' body wrenches (n, 6) that give the team, the ``bodies`` (masses, centres,
    inertias about them, in W: the robots ``holding``, at base poses (rot_base, pos_base), and the
    cargo) joined rigidly, the cargo frame's desired motion (``team_wrench``, then
    ``allocate``); and the saturation ratio."""
    mass, com, inertia = composite_body(*bodies)
    wrench = team_wrench(mass, com, inertia, origin, w, acc, wd)
    return allocate(team, holding, rot_base, pos_base, com, wrench)


# ------------------------------------------------------------------------------- moving arms
# The arms move: every link of robot j moves relative to its grasp frame G_j, which is fixed to
# the cargo. With each link b's centre c_b, velocity v_b and acceleration a_b relative to the
# cargo frame (derivatives taken in it), angular velocity w_b and acceleration al_b relative to
# it, the cargo's angular velocity w and the rigid terms of ``team_wrench``, Newton-Euler for the
# team adds per link
#     F_b = m_b (a_b + 2 w x v_b),
#     tau_b = I_b (al_b + w x w_b) + w x I_b w_b + w_b x I_b w + w_b x I_b w_b   (about c_b),
# and about the team's centre of mass c: [sum F_b; sum tau_b + (c_b - c) x F_b].
# (The arms' kinematics and their motion relative to G: ``arm_kinematics``.)


@njit(cache=True, inline="always")
def _add_into(out: np.ndarray, v: np.ndarray) -> None:
    """out += v (3,), elementwise, without a temporary."""
    for i in range(3):
        out[i] += v[i]


@njit(cache=True)
def arm_motion_wrench(
    masses: np.ndarray,
    coms: np.ndarray,
    inertias: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
    w_rel: np.ndarray,
    al_rel: np.ndarray,
    com: np.ndarray,
    w: np.ndarray,
) -> np.ndarray:
    """The wrench (6,) about ``com`` the arms' motion adds to ``team_wrench`` (section above):
    links b (masses (b,), centres, inertias, relative velocities, accelerations, angular
    velocities and accelerations, one frame's axes) on a cargo turning at ``w``."""
    out, force, torque, term = np.zeros(6), np.empty(3), np.empty(3), np.empty(3)
    inertia_w, inertia_w_rel, lever = np.empty(3), np.empty(3), np.empty(3)
    for b in range(len(masses)):  # in loops on 3-vectors, written into the scratch above
        inertia = inertias[b]
        cross3_into(term, w, vel[b])
        for i in range(3):  # F_b = m_b (a_b + 2 w x v_b)
            force[i] = masses[b] * (acc[b, i] + 2.0 * term[i])
        cross3_into(term, w, w_rel[b])
        for i in range(3):
            term[i] += al_rel[b, i]
        matvec3_into(torque, inertia, term)  # I_b (al_b + w x w_b)
        matvec3_into(inertia_w, inertia, w)
        matvec3_into(inertia_w_rel, inertia, w_rel[b])
        cross3_into(term, w, inertia_w_rel)
        _add_into(torque, term)  # + w x I_b w_b
        cross3_into(term, w_rel[b], inertia_w)
        _add_into(torque, term)  # + w_b x I_b w
        cross3_into(term, w_rel[b], inertia_w_rel)
        _add_into(torque, term)  # + w_b x I_b w_b
        for i in range(3):
            lever[i] = coms[b, i] - com[i]
        cross3_into(term, lever, force)
        for i in range(3):
            out[i] += force[i]
            out[i + 3] += torque[i] + term[i]
    return out


@njit(cache=True)
def place_arm_motion(
    team: TeamModel,
    holding: np.ndarray,
    grasp_rot: np.ndarray,
    grasp_pos: np.ndarray,
    motions: tuple,
    row: np.ndarray,
) -> tuple:
    """``team_arm_motion`` from the arms' motions in their grasp frames, robot j's at row[j] of
    the stacked ``motions`` (``arm_kinematics.arm_motion_into``), rotated into W (robot j's
    grasp frame in W: grasp_rot[j], grasp_pos[j]): x_W = R x_G (+ p for the centres),
    I_W = R I_G R^T."""
    n_links = team.parent.shape[1]
    count = len(holding) * n_links
    masses, coms, inertias = np.empty(count), np.empty((count, 3)), np.empty((count, 3, 3))
    vel, acc = np.empty((count, 3)), np.empty((count, 3))
    w_rel, al_rel = np.empty((count, 3)), np.empty((count, 3))
    base_vel, base_w = np.zeros((len(grasp_rot), 3)), np.zeros((len(grasp_rot), 3))
    rotated = np.empty((3, 3))
    for idx in range(len(holding)):
        j = holding[idx]
        m, r, rot = team.model_of[j], row[j], grasp_rot[j]
        c, inertia, v = motions[0][r], motions[1][r], motions[2][r]
        a, w, al = motions[3][r], motions[4][r], motions[5][r]
        for k in range(n_links):
            b = idx * n_links + k
            masses[b] = team.link_mass[m, k]
            matvec3_into(coms[b], rot, c[k])
            coms[b] += grasp_pos[j]
            matmul3_into(rotated, rot, inertia[k])
            matmul3_into(inertias[b], rotated, rot.T)
            matvec3_into(vel[b], rot, v[k])
            matvec3_into(acc[b], rot, a[k])
            matvec3_into(w_rel[b], rot, w[k])
            matvec3_into(al_rel[b], rot, al[k])
        matvec3_into(base_vel[j], rot, motions[6][r])
        matvec3_into(base_w[j], rot, w[0])
    return masses, coms, inertias, vel, acc, w_rel, al_rel, base_vel, base_w


@njit(cache=True)
def team_arm_motion(
    team: TeamModel,
    holding: np.ndarray,
    grasp_rot: np.ndarray,
    grasp_pos: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
) -> tuple:
    """Every link of the robots ``holding`` with its motion relative to the cargo, in a frame W
    fixed to the cargo in which robot j's grasp frame is (grasp_rot[j], grasp_pos[j]); arms at
    q (n, n_joints) turning at qd: masses, centres, inertias, velocities, accelerations, angular
    velocities and accelerations (``arm_motion_in_grasp`` rotated into W, ``place_arm_motion``),
    and per robot its base origin's velocity (n, 3) and angular velocity (n, 3) relative to the
    cargo (W axes)."""
    n_links = team.parent.shape[1]
    motions, work = empty_arm_motions(len(grasp_rot), n_links), arm_work(n_links)
    for idx in range(len(holding)):
        j = holding[idx]
        arm_motion_into(motions, j, team, team.model_of[j], q[j], qd[j], work)
    row = np.arange(len(grasp_rot))
    return place_arm_motion(team, holding, grasp_rot, grasp_pos, motions, row)


@njit(cache=True)
def team_commands(
    team: TeamModel,
    holding: np.ndarray,
    rot_base: np.ndarray,
    pos_base: np.ndarray,
    q: np.ndarray,
    cargo: tuple[float, np.ndarray, np.ndarray],
    origin: np.ndarray,
    w: np.ndarray,
    acc: np.ndarray,
    wd: np.ndarray,
    qd: np.ndarray,
) -> tuple[np.ndarray, float]:
    """The robots' body wrenches (n, 6) for the robots ``holding`` at base poses (rot_base,
    pos_base) in W and arm angles q (n, n_joints) turning at qd (rad/s), with the ``cargo`` body
    (mass, centre, inertia in W): ``team_wrench`` of the composite body plus
    ``arm_motion_wrench`` of the arms' motion (robot j's grasp frame in W: R_j R_bg(q_j),
    p_j + R_j p_bg(q_j)), allocated by ``allocate``; and the saturation ratio."""
    count = len(holding) + 1
    masses, coms, inertias = np.empty(count), np.empty((count, 3)), np.empty((count, 3, 3))
    grasp_rot, grasp_pos = np.zeros_like(rot_base), np.zeros_like(pos_base)
    for idx in range(len(holding)):
        j = holding[idx]
        mass, com, inertia, rot_bg, pos_bg = robot_body(team, team.model_of[j], q[j])
        masses[idx] = mass
        coms[idx], inertias[idx] = place_body(com, inertia, rot_base[j], pos_base[j])
        grasp_rot[j] = rot_base[j] @ rot_bg
        grasp_pos[j] = pos_base[j] + rot_base[j] @ pos_bg
    masses[-1], coms[-1], inertias[-1] = cargo
    mass, com, inertia = composite_body(masses, coms, inertias)
    wrench = team_wrench(mass, com, inertia, origin, w, acc, wd)
    arms = team_arm_motion(team, holding, grasp_rot, grasp_pos, q, qd)
    wrench += arm_motion_wrench(*arms[:7], com, w)
    return allocate(team, holding, rot_base, pos_base, com, wrench)
