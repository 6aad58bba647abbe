"""The arms' kinematics and their motion relative to the grasp frames, compiled.

Robot j's arm (links k = 1..L-1, parent p, joint angle q_k, unit axis e_k), in its base frame:
    R_k = R_p R_pk0 exp(e_k q_k),    p_k = p_p + R_p p_pk.
In its grasp frame G (fixed to link g at (R_gG, p_gG); G in the base: R_bg = R_g R_gG,
p_bg = p_g + R_g p_gG), link k's rotation, origin and centre of mass (c_k in the link frame):
    R_Gk = R_bg^T R_k,    o_Gk = R_bg^T (p_k - p_bg),    c_Gk = o_Gk + R_Gk c_k.
The links' motion relative to G with the joints at q turning at qd (q(t) = q + qd t), by central
differences over h = ``ARM_STEP_S``:
    v = (c(h) - c(-h)) / 2h,    a = (c(h) - 2 c(0) + c(-h)) / h^2,
    w(+-h/2) = +-log(R(+-h) R(0)^T)^(+-1) / h,    w = mean,    al = (w(h/2) - w(-h/2)) / h,
and the inertias about the centres in G's axes, R_Gk I_k R_Gk^T. Metres, seconds, radians.

The ``_into`` forms write into scratch (``ArmWork``, made once per call of the controller) and
into a row of stacked results (``empty_arm_motions``), with the 3x3 products as loops
(``geometry.matmul3_into``), no allocation and no BLAS call; ``link_frames``,
``links_in_grasp`` and ``arm_motion_in_grasp`` are the same computations returning new arrays.
The robots' models come as one ``team_dynamics.TeamModel``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import exp_so3_into, log_so3_into, matmul3_into, matvec3_into

ARM_STEP_S = 0.01  # central-difference step of the arms' relative motion


class ArmWork(NamedTuple):
    """Scratch for one arm's kinematics at three joint angles: q, q + qd h, q - qd h."""

    q: np.ndarray  # (3, L-1) rad, the three joint angles
    rots: np.ndarray  # (3, L, 3, 3) link frames in the base
    poss: np.ndarray  # (3, L, 3) m
    coms: np.ndarray  # (3, L, 3) m, link centres in the grasp frame
    rots_g: np.ndarray  # (3, L, 3, 3) link rotations in the grasp frame
    origins: np.ndarray  # (3, L, 3) m, link origins in the grasp frame
    mat: np.ndarray  # (3, 3, 3) scratch 3x3 products
    vec: np.ndarray  # (3, 3) scratch 3-vectors


@njit(cache=True)
def arm_work(n_links: int) -> ArmWork:
    """Room for ``ArmWork`` of an arm with ``n_links`` links (base included)."""
    return ArmWork(
        np.empty((3, n_links - 1)),
        np.empty((3, n_links, 3, 3)),
        np.empty((3, n_links, 3)),
        np.empty((3, n_links, 3)),
        np.empty((3, n_links, 3, 3)),
        np.empty((3, n_links, 3)),
        np.empty((3, 3, 3)),
        np.empty((3, 3)),
    )


@njit(cache=True)
def link_frames_into(
    rots: np.ndarray, poss: np.ndarray, team, m: int, q: np.ndarray, work: ArmWork
) -> None:
    """rots (L, 3, 3), poss (L, 3) = model m's link frames in its base at joint angles q
    (L-1,) rad: R_k = R_p R_pk0 exp(e_k q_k), p_k = p_p + R_p p_pk."""
    mat, vec = work.mat, work.vec
    for i in range(3):
        for j in range(3):
            rots[0, i, j] = 1.0 if i == j else 0.0
        poss[0, i] = 0.0
    for k in range(1, rots.shape[0]):
        p = team.parent[m, k]
        for i in range(3):
            vec[0, i] = team.joint_axis[m, k, i] * q[k - 1]
        exp_so3_into(mat[0], vec[0])  # exp(e_k q_k)
        matmul3_into(mat[1], rots[p], team.rot_in_parent[m, k])
        matmul3_into(rots[k], mat[1], mat[0])
        matvec3_into(vec[1], rots[p], team.pos_in_parent[m, k])
        for i in range(3):
            poss[k, i] = poss[p, i] + vec[1, i]


@njit(cache=True)
def grasp_frames_into(
    coms: np.ndarray,
    rots_g: np.ndarray,
    origins: np.ndarray,
    team,
    m: int,
    rots: np.ndarray,
    poss: np.ndarray,
    work: ArmWork,
) -> None:
    """coms (L, 3), rots_g (L, 3, 3), origins (L, 3) = model m's link centres, rotations and
    origins in its grasp frame G, from its link frames in the base (rots, poss):
    R_Gk = R_bg^T R_k, o_Gk = R_bg^T (p_k - p_bg), c_Gk = o_Gk + R_Gk c_k."""
    mat, vec, g = work.mat, work.vec, team.grasp_link[m]
    matmul3_into(mat[0], rots[g], team.grasp_rot[m])  # R_bg
    rot_gb = mat[0].T
    matvec3_into(vec[0], rots[g], team.grasp_pos[m])
    for i in range(3):
        vec[0, i] += poss[g, i]  # p_bg
    for k in range(rots.shape[0]):
        matmul3_into(rots_g[k], rot_gb, rots[k])
        for i in range(3):
            vec[1, i] = poss[k, i] - vec[0, i]
        matvec3_into(origins[k], rot_gb, vec[1])
        matvec3_into(vec[2], rots_g[k], team.link_com[m, k])
        for i in range(3):
            coms[k, i] = origins[k, i] + vec[2, i]


@njit(cache=True)
def empty_arm_motions(count: int, n_links: int) -> tuple:
    """Room for ``count`` results of ``arm_motion_in_grasp`` stacked by row: centres, inertias,
    velocities, accelerations, angular velocities and accelerations (count, L, ...), base
    origin velocities (count, 3)."""
    return (
        np.empty((count, n_links, 3)),
        np.empty((count, n_links, 3, 3)),
        np.empty((count, n_links, 3)),
        np.empty((count, n_links, 3)),
        np.empty((count, n_links, 3)),
        np.empty((count, n_links, 3)),
        np.empty((count, 3)),
    )


@njit(cache=True)
def arm_motion_into(
    motions: tuple, r: int, team, m: int, q: np.ndarray, qd: np.ndarray, work: ArmWork
) -> None:
    """Row r of the stacked ``motions`` = ``arm_motion_in_grasp`` of model m at joint angles q
    (rad) turning at qd (rad/s); ``work`` keeps the link frames at q (``work.rots[0]``,
    ``work.poss[0]``) for the caller."""
    h = ARM_STEP_S
    for i in range(len(q)):
        work.q[0, i], work.q[1, i], work.q[2, i] = q[i], q[i] + qd[i] * h, q[i] - qd[i] * h
    for s in range(3):  # at q, q + qd h, q - qd h
        rots, poss = work.rots[s], work.poss[s]
        link_frames_into(rots, poss, team, m, work.q[s], work)
        grasp_frames_into(work.coms[s], work.rots_g[s], work.origins[s], team, m, rots, poss, work)
    (c0, cp, cm), (r0, rp, rm), mat, vec = work.coms, work.rots_g, work.mat, work.vec
    centres, inertias, vel, acc, w, al, base_vel = motions
    for k in range(len(c0)):
        for i in range(3):
            centres[r, k, i] = c0[k, i]
            vel[r, k, i] = (cp[k, i] - cm[k, i]) / (2 * h)
            acc[r, k, i] = (cp[k, i] - 2 * c0[k, i] + cm[k, i]) / (h * h)
        matmul3_into(mat[0], r0[k], team.link_inertia[m, k])
        matmul3_into(inertias[r, k], mat[0], r0[k].T)  # about c_b, G axes
        matmul3_into(mat[1], rp[k], r0[k].T)
        log_so3_into(vec[0], mat[1])
        matmul3_into(mat[2], r0[k], rm[k].T)
        log_so3_into(vec[1], mat[2])
        for i in range(3):
            w_up, w_down = vec[0, i] / h, vec[1, i] / h
            w[r, k, i] = 0.5 * (w_up + w_down)
            al[r, k, i] = (w_up - w_down) / h
    for i in range(3):
        base_vel[r, i] = (work.origins[1, 0, i] - work.origins[2, 0, i]) / (2 * h)


@njit(cache=True)
def link_frames(team, m: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model m's link frames in its base frame at joint angles q (L-1,) rad: rotations (L, 3, 3)
    and origins (L, 3) m (``link_frames_into``)."""
    n_links = team.parent.shape[1]
    rots, poss = np.empty((n_links, 3, 3)), np.empty((n_links, 3))
    link_frames_into(rots, poss, team, m, q, arm_work(n_links))
    return rots, poss


@njit(cache=True)
def links_in_grasp(team, m: int, q: np.ndarray) -> tuple:
    """Model m's links at joint angles q in its grasp frame G: centres of mass (L, 3) m,
    rotations (L, 3, 3) and the link frames' origins (L, 3) m (``grasp_frames_into``)."""
    n_links = team.parent.shape[1]
    work = arm_work(n_links)
    rots, poss = link_frames(team, m, q)
    coms, rots_g = np.empty((n_links, 3)), np.empty((n_links, 3, 3))
    origins = np.empty((n_links, 3))
    grasp_frames_into(coms, rots_g, origins, team, m, rots, poss, work)
    return coms, rots_g, origins


@njit(cache=True)
def arm_motion_in_grasp(team, m: int, q: np.ndarray, qd: np.ndarray) -> tuple:
    """Motion of model m's links relative to its grasp frame G (G axes) with the joints at q
    (rad) turning at qd (rad/s): centres c_b (L, 3), inertias (L, 3, 3) about them, the
    centres' velocities v_b and accelerations a_b (L, 3), angular velocities w_b and
    accelerations al_b (L, 3), and the base origin's velocity (3,) (module docstring)."""
    n_links = team.parent.shape[1]
    motions = empty_arm_motions(1, n_links)
    arm_motion_into(motions, 0, team, m, q, qd, arm_work(n_links))
    c, inertias, v, a, w, al, v_base = motions
    return c[0], inertias[0], v[0], a[0], w[0], al[0], v_base[0]
