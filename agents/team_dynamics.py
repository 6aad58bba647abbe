"""The team as one rigid body: composite inertia, desired wrench and its allocation, compiled.

The cooperative controllers (``controllers.py``) treat the robots and the cargo as one rigid body
(the arms move slowly; their own motion is a disturbance the feedback absorbs). Every function
here works in one frame W (the world, or one robot's base frame: the equations are the same), with
vectors in metres, seconds, radians, kilograms, and wrenches [force (N); moment (N m)].

Kinematics of robot j's arm (links k = 1..L-1, parent p, joint angle q_k, unit axis e_k):
    R_k = R_p R_pk0 exp(e_k q_k),    p_k = p_p + R_p p_pk             (link frames in its base)

Composite body of bodies b (robot links and the cargo), mass m_b, centre c_b and inertia I_b about
c_b (W axes), by the parallel-axis theorem:
    M = sum m_b,   c = sum m_b c_b / M,  I_c = sum I_b + m_b (|r_b|^2 1 - r_b r_b^T), r_b = c_b - c

Desired motion of the cargo frame (PD with feed-forward, Astrobee's law, facts file section 3.1):
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
``TeamModel`` of arrays stacked over robots (``team_model``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import exp_so3, skew
from astrocargo.estimator.rne import RobotDescription


class TeamModel(NamedTuple):
    """The robots' known models as arrays stacked over n robots of L links each (base first)."""

    parent: np.ndarray  # (n, L) int64, parent link of each link (unused for the base)
    rot_in_parent: np.ndarray  # (n, L, 3, 3) link frame at q = 0 in its parent's frame
    pos_in_parent: np.ndarray  # (n, L, 3) m, link origin in its parent's frame
    joint_axis: np.ndarray  # (n, L, 3) unit joint axis in the link frame (zeros for the base)
    link_mass: np.ndarray  # (n, L) kg
    link_com: np.ndarray  # (n, L, 3) m, centre of mass in the link frame
    link_inertia: np.ndarray  # (n, L, 3, 3) kg m^2 about the centre of mass, link axes
    grasp_link: np.ndarray  # (n,) int64, the link the grasp frame is fixed to
    grasp_rot: np.ndarray  # (n, 3, 3) grasp frame in that link's frame
    grasp_pos: np.ndarray  # (n, 3) m
    thrust_limit: np.ndarray  # (n, 6) N, N m: body force and torque limits


def team_model(robots: list[RobotDescription]) -> TeamModel:
    """Stack the robots' models. They must share one arm structure (the same number of links)."""
    if not robots:
        raise ValueError("team_model needs at least one robot")
    n_links = {len(r.links) for r in robots}
    if len(n_links) != 1:
        raise ValueError(f"robots must all have the same number of links, got {sorted(n_links)}")

    def stack(get, dtype=float) -> np.ndarray:
        return np.ascontiguousarray([[get(link) for link in r.links] for r in robots], dtype=dtype)

    return TeamModel(
        parent=stack(lambda k: max(k.parent, 0), np.int64),
        rot_in_parent=stack(lambda k: k.rot_in_parent),
        pos_in_parent=stack(lambda k: k.pos_in_parent),
        joint_axis=stack(lambda k: np.zeros(3) if k.joint_axis is None else k.joint_axis),
        link_mass=stack(lambda k: k.mass),
        link_com=stack(lambda k: k.com),
        link_inertia=stack(lambda k: k.inertia_com),
        grasp_link=np.array([r.grasp_link for r in robots], dtype=np.int64),
        grasp_rot=np.ascontiguousarray([r.grasp_rot for r in robots], dtype=float),
        grasp_pos=np.ascontiguousarray([r.grasp_pos for r in robots], dtype=float),
        thrust_limit=np.ascontiguousarray([r.thrust_limit for r in robots], dtype=float),
    )


@njit(cache=True)
def link_frames(team: TeamModel, j: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robot j's link frames in its base frame at joint angles q (L-1,) rad: rotations (L, 3, 3)
    and origins (L, 3) m, R_k = R_p R_pk0 exp(e_k q_k), p_k = p_p + R_p p_pk."""
    n_links = team.parent.shape[1]
    rots = np.empty((n_links, 3, 3))
    poss = np.zeros((n_links, 3))
    rots[0] = np.eye(3)
    for k in range(1, n_links):
        p = team.parent[j, k]
        joint = exp_so3(team.joint_axis[j, k] * q[k - 1])
        rots[k] = rots[p] @ team.rot_in_parent[j, k] @ joint
        poss[k] = poss[p] + rots[p] @ team.pos_in_parent[j, k]
    return rots, poss


@njit(cache=True)
def grasp_frame(team: TeamModel, j: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robot j's grasp frame in its base frame at joint angles q: rotation and origin (m)."""
    rots, poss = link_frames(team, j, q)
    g = team.grasp_link[j]
    return rots[g] @ team.grasp_rot[j], poss[g] + rots[g] @ team.grasp_pos[j]


@njit(cache=True)
def body_from_params(
    params: np.ndarray, rot: np.ndarray, pos: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (m) and inertia about it (kg m^2) in frame W of a body whose
    standard parameters pi = [m, m c, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (I about the origin)
    are given in frame A, A's pose in W being (rot, pos): c = h / m,
    I_c = I_o - m (|c|^2 1 - c c^T), then c_W = R c + p and I_W = R I_c R^T."""
    mass = params[0]
    com = params[1:4] / mass
    xx, yy, zz, xy, xz, yz = params[4:10]
    inertia_o = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    inertia_com = inertia_o - mass * ((com @ com) * np.eye(3) - np.outer(com, com))
    return mass, rot @ com + pos, rot @ inertia_com @ rot.T


@njit(cache=True)
def composite_body(
    masses: np.ndarray, coms: np.ndarray, inertias: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and inertia about it of rigidly joined bodies (b,), (b, 3),
    (b, 3, 3) (each about its own centre), by the parallel-axis theorem."""
    mass = masses.sum()
    com = (masses @ coms) / mass
    inertia = np.zeros((3, 3))
    for b in range(len(masses)):
        r = coms[b] - com
        inertia += inertias[b] + masses[b] * ((r @ r) * np.eye(3) - np.outer(r, r))
    return mass, com, inertia


@njit(cache=True)
def team_bodies(
    team: TeamModel,
    holding: np.ndarray,
    rot_base: np.ndarray,
    pos_base: np.ndarray,
    q: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every link of the robots ``holding`` as a body in W: masses, centres (m) and inertias
    about them, from each base pose (rot_base[j], pos_base[j]) and arm angles q[j]."""
    n_links = team.parent.shape[1]
    count = len(holding) * n_links
    masses, coms, inertias = np.empty(count), np.empty((count, 3)), np.empty((count, 3, 3))
    for idx in range(len(holding)):
        j = holding[idx]
        rots, poss = link_frames(team, j, q[j])
        for k in range(n_links):
            b = idx * n_links + k
            rot = rot_base[j] @ rots[k]
            masses[b] = team.link_mass[j, k]
            coms[b] = rot_base[j] @ (rots[k] @ team.link_com[j, k] + poss[k]) + pos_base[j]
            inertias[b] = rot @ team.link_inertia[j, k] @ rot.T
    return masses, coms, inertias


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
    force = mass * (acc + np.cross(wd, r) + np.cross(w, np.cross(w, r)))
    torque = inertia @ wd + np.cross(w, inertia @ w)
    return np.concatenate((force, torque))


@njit(cache=True)
def wrench_map(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """G (6, 6): a wrench [f; n about A's origin] in frame A to W about W's origin, A's pose in W
    being (rot, pos): f_W = R f, n_W = R n + pos x (R f)."""
    g = np.zeros((6, 6))
    g[:3, :3] = rot
    g[3:, 3:] = rot
    g[3:, :3] = skew(pos) @ rot
    return g


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
    maps = np.empty((len(holding), 6, 6))
    normal = np.zeros((6, 6))
    for idx in range(len(holding)):
        j = holding[idx]
        maps[idx] = wrench_map(rot_base[j], pos_base[j] - com)
        normal += (maps[idx] * team.thrust_limit[j] ** 2) @ maps[idx].T
    lam = np.linalg.solve(normal, wrench)
    commands = np.zeros((len(rot_base), 6))
    ratio = 0.0
    for idx in range(len(holding)):
        j = holding[idx]
        commands[j] = team.thrust_limit[j] ** 2 * (maps[idx].T @ lam)
        ratio = max(ratio, np.max(np.abs(commands[j]) / team.thrust_limit[j]))
    if ratio > 1.0:
        commands /= ratio
    return commands, ratio


@njit(cache=True)
def thrust_commands(
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
) -> tuple[np.ndarray, float]:
    """The robots' body wrenches (n, 6) that give the team (the robots ``holding`` at base poses
    (rot_base, pos_base) and arm angles q, plus the ``cargo`` body (mass, centre, inertia in W))
    the cargo frame's desired motion (``team_wrench``, then ``allocate``); and the saturation
    ratio."""
    masses, coms, inertias = team_bodies(team, holding, rot_base, pos_base, q)
    cargo_mass, cargo_com, cargo_inertia = cargo
    masses = np.append(masses, cargo_mass)
    coms = np.concatenate((coms, cargo_com.reshape(1, 3)))
    inertias = np.concatenate((inertias, cargo_inertia.reshape(1, 3, 3)))
    mass, com, inertia = composite_body(masses, coms, inertias)
    wrench = team_wrench(mass, com, inertia, origin, w, acc, wd)
    return allocate(team, holding, rot_base, pos_base, com, wrench)
