"""The controller's arm kinematics (agents/arm_kinematics.py) against the estimator's forward
kinematics and against fine numerical derivatives, and the scratch-writing forms of the team's
kernels against the products they stand for."""

import numpy as np

from astrocargo.agents.arm_kinematics import (
    arm_motion_in_grasp,
    arm_motion_into,
    arm_work,
    empty_arm_motions,
    link_frames,
    links_in_grasp,
)
from astrocargo.agents.team_dynamics import (
    place_body_into,
    team_model,
    wrench_map_into,
)
from astrocargo.envs.world import World
from astrocargo.estimator.geometry import exp_so3, log_so3, skew
from astrocargo.estimator.rne import grasp_pose, link_poses

ROBOT = World(1).robot_model(0)
TEAM = team_model([ROBOT])
RNG = np.random.default_rng(7)
ANGLES = RNG.uniform(-2.0, 2.0, (4, ROBOT.n_joints))
RATES = RNG.uniform(-0.4, 0.4, (4, ROBOT.n_joints))


def test_links_in_grasp_are_the_estimator_link_poses_in_the_grasp_frame():
    """R_Gk = R_bg^T R_k, o_Gk = R_bg^T (p_k - p_bg), c_Gk = o_Gk + R_Gk c_k, with the link
    frames and the grasp pose from rne (another implementation of the same kinematics)."""
    coms_link = np.array([k.com for k in ROBOT.links])
    for q in ANGLES:
        rots, poss = link_poses(ROBOT, q)
        rot_bg, pos_bg = grasp_pose(ROBOT, q)
        got_rots, got_poss = link_frames(TEAM, 0, q)
        np.testing.assert_allclose(got_rots, rots, atol=1e-14)
        np.testing.assert_allclose(got_poss, poss, atol=1e-14)
        coms, rots_g, origins = links_in_grasp(TEAM, 0, q)
        want_rots = np.einsum("ji,kjl->kil", rot_bg, rots)
        want_origins = (poss - pos_bg) @ rot_bg
        np.testing.assert_allclose(rots_g, want_rots, atol=1e-14)
        np.testing.assert_allclose(origins, want_origins, atol=1e-14)
        want_coms = want_origins + np.einsum("kij,kj->ki", want_rots, coms_link)
        np.testing.assert_allclose(coms, want_coms, atol=1e-14)


def _fine_motion(q, qd, h):
    """Velocities, accelerations and angular velocities of the links in G by central
    differences of ``links_in_grasp`` over a small step h (an independent check of the
    controller's differences over ARM_STEP_S)."""
    up, mid, down = (links_in_grasp(TEAM, 0, q + s * qd * h) for s in (1.0, 0.0, -1.0))
    vel = (up[0] - down[0]) / (2 * h)
    acc = (up[0] - 2 * mid[0] + down[0]) / h**2
    w = np.array([log_so3(a @ b.T) for a, b in zip(up[1], down[1], strict=True)]) / (2 * h)
    return vel, acc, w, (up[2][0] - down[2][0]) / (2 * h)


def test_arm_motion_is_the_derivative_of_the_links_in_the_grasp_frame():
    """The links' motion relative to G at q turning at qd (differences over ARM_STEP_S = 0.01 s,
    error O(h^2 qd^2) relative) equals finer differences: velocities and angular velocities to
    1e-4 of their largest entry, accelerations to 1e-3; the inertias are R_Gk I_k R_Gk^T."""
    inertias_link = np.array([k.inertia_com for k in ROBOT.links])
    for q, qd in zip(ANGLES, RATES, strict=True):
        c, inertias, vel, acc, w, _, base_vel = arm_motion_in_grasp(TEAM, 0, q, qd)
        fine_vel, _, fine_w, fine_base = _fine_motion(q, qd, 1e-6)
        _, fine_acc, _, _ = _fine_motion(q, qd, 1e-4)
        scale = np.abs(fine_vel).max()
        np.testing.assert_allclose(vel, fine_vel, atol=1e-4 * scale)
        np.testing.assert_allclose(base_vel, fine_base, atol=1e-4 * scale)
        np.testing.assert_allclose(w, fine_w, atol=1e-4 * np.abs(fine_w).max())
        np.testing.assert_allclose(acc, fine_acc, atol=1e-3 * np.abs(fine_acc).max())
        coms, rots_g, _ = links_in_grasp(TEAM, 0, q)
        np.testing.assert_array_equal(c, coms)
        want = np.einsum("kij,kjl,kml->kim", rots_g, inertias_link, rots_g)
        np.testing.assert_allclose(inertias, want, atol=1e-15)


def test_arm_motion_into_writes_its_row_only():
    """``arm_motion_into`` fills row r of the stacked motions with ``arm_motion_in_grasp`` bit
    for bit, leaves the other rows as they were, and keeps the link frames at q in the work."""
    n_links = TEAM.parent.shape[1]
    motions, work = empty_arm_motions(3, n_links), arm_work(n_links)
    for part in motions:
        part[:] = np.nan
    q, qd = ANGLES[1], RATES[1]
    arm_motion_into(motions, 1, TEAM, 0, q, qd, work)
    for part, want in zip(motions, arm_motion_in_grasp(TEAM, 0, q, qd), strict=True):
        np.testing.assert_array_equal(part[1], want)
        assert np.isnan(part[0]).all() and np.isnan(part[2]).all()
    rots, poss = link_frames(TEAM, 0, q)
    np.testing.assert_array_equal(work.rots[0], rots)
    np.testing.assert_array_equal(work.poss[0], poss)


def test_scratch_forms_are_the_products():
    """wrench_map_into: G = [[R, 0], [[p]x R, R]] over a dirty G; place_body_into: R c + p and
    R I R^T (to rounding of the 3x3 products)."""
    rot, pos = exp_so3(RNG.normal(size=3)), RNG.normal(size=3)
    g = np.full((6, 6), np.nan)
    wrench_map_into(g, rot, pos, np.empty((3, 3)))
    want = np.block([[rot, np.zeros((3, 3))], [skew(pos) @ rot, rot]])
    np.testing.assert_allclose(g, want, rtol=0, atol=1e-15)
    com, inertia = RNG.normal(size=3), np.diag([0.3, 0.2, 0.1]) + 0.01
    com_w, inertia_w = np.empty(3), np.empty((3, 3))
    place_body_into(com_w, inertia_w, com, inertia, rot, pos, np.empty((3, 3)))
    np.testing.assert_allclose(com_w, rot @ com + pos, rtol=0, atol=1e-15)
    np.testing.assert_allclose(inertia_w, rot @ inertia @ rot.T, rtol=0, atol=1e-15)
