"""The reward terms (the env docstring's section Rewards): per robot, the team's and its own
(individual) value of each term, mixed as shared * team + (1 - shared) * individual and
weighted; the reward is their sum. ``observe_and_reward`` is the step's one compiled call after
the physics, sensing and navigation (without estimators, in the same call as them:
``step_kernels``): the observations (``envs.observations``), then the rewards.

Tracking term: -(|p - p_ref| + ROTATION_WEIGHT_M_PER_RAD |log(R_ref^T R)|) of the true cargo
frame pose (p, R) against the reference (p_ref, R_ref), m and rad."""

from __future__ import annotations

import numpy as np
from numba import njit

from astrocargo.envs.observations import assemble
from astrocargo.estimator.checks import all_finite
from astrocargo.estimator.geometry import log_so3, matmul3

ROTATION_WEIGHT_M_PER_RAD = 0.5  # tracking term: metres of position error per radian


@njit(cache=True)
def mix_rewards(track, effort, info, robot_contacts, cargo_contacts, acting, weights, shared,
                mixed, rewards):  # fmt: skip
    """Weighted, mixed terms into ``mixed`` (4, N) in ``REWARD_TERMS`` order and their sum per
    robot into ``rewards`` (N,).

    ``track`` (the team's tracking term, the same for every robot) is a scalar; the effort term
    is -``effort`` and ``info`` (N,) is individual; the contact term is -(a robot's own contacts
    + the cargo's), its team value -(every contact). The team value of effort and info is their
    mean over the ``acting`` robots; the others' entries are 0."""
    n = effort.shape[0]
    individual = np.empty((4, n))
    for i in range(n):
        individual[0, i], individual[1, i], individual[2, i] = track, -effort[i], info[i]
        individual[3, i] = -float(robot_contacts[i] + cargo_contacts)
    count = 0
    for i in range(n):
        count += acting[i]
    team = np.empty(4)
    for t in range(4):
        total = 0.0
        for i in range(n):
            if acting[i]:
                total += individual[t, i]
        team[t] = total / count
    team[0], team[3] = track, -float(robot_contacts.sum() + cargo_contacts)
    mixed[:] = 0.0
    rewards[:] = 0.0
    for i in range(n):
        if not acting[i]:
            continue
        for t in range(4):
            mixed[t, i] = weights[t] * (shared * team[t] + (1.0 - shared) * individual[t, i])
            rewards[i] += mixed[t, i]


@njit(cache=True)
def tracking_errors(pos, rot, ref_pos, ref_rot):
    """Position error |p - p_ref| (m) and rotation angle error |log(R_ref^T R)| (rad)."""
    angle = log_so3(matmul3(ref_rot.T, rot))
    pos_sq, angle_sq = 0.0, 0.0
    for i in range(3):
        offset = pos[i] - ref_pos[i]
        pos_sq += offset * offset
        angle_sq += angle[i] * angle[i]
    return np.sqrt(pos_sq), np.sqrt(angle_sq)


@njit(cache=True)
def observe_and_reward(obs, acting, own_starts, peer_starts, estimate_start, link_parent, arms,
                       nav, q, target, ref, peers, estimates, qd, cargo_pose, finite, effort,
                       info, contacts, weights, shared, mixed, rewards):  # fmt: skip
    """The observations of the ``acting`` robots into ``obs`` (N, obs_dim), zeros elsewhere
    (``assemble``, whose arguments these are: the layout's starts, the arms, the navigation
    filters ``nav`` ...; ``ref`` the reference's arrays, ``peers`` the peer slots' (wrench, age,
    valid, arm)); a non-finite entry is zeroed and makes the step not ``finite``.
    Then the weighted, mixed terms ``mixed`` (4, N) and ``rewards`` (N,) of ``mix_rewards``:
    tracking of the cargo pose ``cargo_pose`` (xpos, xmat, cargo body) when finite, else 0;
    effort -``effort``; ``info``; ``contacts`` (per robot (N,), the cargo's). Returns finite."""
    obs[:] = 0.0
    assemble(
        obs, acting, own_starts, peer_starts, estimate_start, link_parent, arms, nav, q, target,
        ref[0], ref[1], ref[2], peers[0], peers[1], peers[2], estimates, qd, peers[3],
    )  # fmt: skip
    if not all_finite(obs):
        finite = False
        flat = obs.ravel()
        for k in range(flat.shape[0]):
            if not np.isfinite(flat[k]):
                flat[k] = 0.0
    track = 0.0
    if finite:
        xpos, xmat, body = cargo_pose
        pos_err, angle_err = tracking_errors(
            xpos[body], xmat[body].reshape(3, 3), ref[1][0], ref[0]
        )
        track = -(pos_err + ROTATION_WEIGHT_M_PER_RAD * angle_err)
    mix_rewards(
        track, effort, info, contacts[0], contacts[1], acting, weights, shared, mixed, rewards
    )
    return finite
