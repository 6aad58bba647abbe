"""A control step's compiled calls, each over the arrays of the step's record (``world``, bound
once per world: ``transport.CargoTransport._bind_step_record``, ``estimator.records``):

- ``commands``, before the physics: the period's commands (``actions.command_period``) and
  whether qpos and qvel are as the last period left them, within MuJoCo's bounds
  (``physics.same_state``);
- ``sense_and_navigate``, after it: the physics state's check (``physics.state_finite``), every
  robot's sensor readings (``sensors.read_into``) with the faults' masks of the step, and the
  robots' navigation filters (``navigation.navigate``);
- ``observe_and_reward``, after the estimators: the reference at the step's end
  (``trajectories.evaluate_into``), the observations and rewards (``rewards.observe_and_reward``);
- ``sense_observe_and_reward``: the last two in one call, for a step without estimators
  (nothing between them, and no peer slots or estimates to pass) and without a release.

Each runs the same kernels the separate calls would, with the same arithmetic; the record
passes their arrays across the Python boundary as one argument (numba checks and unboxes every
argument at every call, which costs more than the arithmetic of two robots).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from astrocargo.agents.trajectories import evaluate_into
from astrocargo.envs.actions import command_period
from astrocargo.envs.navigation import navigate
from astrocargo.envs.physics import same_state, state_finite
from astrocargo.envs.rewards import observe_and_reward as observe_and_reward_arrays
from astrocargo.envs.sensors import read_into


@njit(cache=True)
def commands(actions, normals, thrust_scale, ctrl, world, qpos, qvel, thrust):
    """``command_period`` of ``actions`` (N, 8) with the step's standard ``normals``, the
    faults' ``thrust_scale`` (H,) and MuJoCo's ``ctrl``; the record ``world`` gives the control
    period ``dt_s`` and the servos' move in it, the limits, the actuators, the arms' targets and
    rates and the step's clipping, effort and saturation (written in place); the thrust commands
    go to ``thrust`` (N, 6). Returns whether ``qpos`` and ``qvel`` are still those the record
    saved (saved_qpos, saved_qvel) and within MuJoCo's bounds (``same_state``: the period may
    skip the stages and checks the last one left)."""
    w = world[0]
    command_period(
        actions, w.acting, w.thrust_limits, w.joint_low, w.joint_high, w.max_move_rad[0],
        w.dt_s[0], w.arm_targets, w.arm_rates, normals, w.actuation_std, thrust_scale, w.rows,
        w.thrust_ctrl, w.arm_ctrl, ctrl, w.n_clipped, w.effort, w.saturation, thrust,
    )  # fmt: skip
    return same_state(qpos, qvel, w.saved_qpos, w.saved_qvel)


@njit(cache=True)
def observe_and_reward(obs, rewards, acting, world, readings, nav, arms, xpos, xmat, peers,
                       estimates, info, robot_contacts, cargo_contacts, finite, shapes,
                       time_s):  # fmt: skip
    """``rewards.observe_and_reward`` into ``obs`` (N, obs_dim) and ``rewards`` (N,) of the
    robots ``acting`` at this step (bool (N,): those letting go at its end included, whom the
    record of the world after a release no longer counts): the layout, the reference, the arms'
    targets and rates, the effort, the weights and the mixed terms from the record ``world``;
    the encoders from ``readings``; ``nav`` the navigation filters, ``arms`` the arm models
    (``ObservationBuilder.arms``), ``xpos`` / ``xmat`` MuJoCo's body poses, ``peers`` the peer
    slots' (wrench, age, valid, arm), ``estimates`` (N, 20) or (N, 0), ``info`` (N,), the wall
    contacts per robot and of the cargo. The reference first: the analytic trajectory's
    ``shapes`` (1,) (``trajectories.SHAPE_DTYPE``) evaluated at the step's end ``time_s`` (s) into
    the record's ref_rot, ref_vecs, ref_pan (``trajectories.evaluate_into``); with ``shapes``
    empty (0,) they already hold it (a designed trajectory, written by the caller). Returns
    finite."""
    w = world[0]
    if shapes.shape[0] == 1:
        evaluate_into(w.ref_rot, w.ref_vecs, w.ref_pan, time_s, shapes)
    return observe_and_reward_arrays(
        obs, acting, w.own_starts, w.peer_starts, w.estimate_start[0], w.link_parent, arms,
        nav, readings[0].joints, w.arm_targets, (w.ref_rot, w.ref_vecs, w.ref_pan), peers,
        estimates, w.arm_rates, (xpos, xmat, w.cargo_body[0]), finite, w.effort, info,
        (robot_contacts, cargo_contacts), w.weights, w.shared[0], w.mixed, rewards,
    )  # fmt: skip


@njit(cache=True)
def sense_and_navigate(
    qpos, qvel, warnings, cvel, site_xpos, site_xmat, subtree_com, sensordata, period_s, normals,
    fix, world, readings, filters,
):  # fmt: skip
    """After the physics of a period: whether its state is finite (``state_finite``, which also
    saves qpos and qvel in the record's saved_qpos, saved_qvel); the readings (``read_into``: the
    H robots of the world in its ``rows``; their noise: the standard normals ``normals`` after
    the propulsion's first 6 H, as (H, draws), times ``noise_std``) into ``readings``
    (``sensors.readings_record``), whose IMU frames and fixes are then kept only where
    ``imu_ok`` / ``fix_ok`` (bool (N,): what the faults leave); the navigation ``filters`` of
    the ``acting`` robots over the control period ``dt_s`` (``navigate``). ``world``: the step's
    record (``transport.CargoTransport._bind_step_record``: unstable, imu_index, joint_adr,
    pos_adr, quat_adr, noise_std, rows, imu_v0, imu_r0, imu_ok, fix_ok, acting, dt_s,
    saved_qpos, saved_qvel). Returns whether the state is finite."""
    w, r = world[0], readings[0]
    h = w.rows.shape[0]
    draws = (normals.shape[0] - 6 * h) // h
    noise = w.noise_std[:draws] * normals[6 * h :].reshape(h, draws)
    finite = state_finite(qpos, qvel, warnings, w.unstable, w.saved_qpos, w.saved_qvel)
    read_into(
        w.imu_v0, w.imu_r0, period_s, cvel, site_xpos, site_xmat, subtree_com, w.imu_index,
        sensordata, w.joint_adr, w.pos_adr, w.quat_adr, noise, fix, w.rows, r.accel, r.gyro,
        r.joints, r.pos, r.quat, r.has_imu, r.has_fix,
    )  # fmt: skip
    for i in range(r.has_imu.shape[0]):
        r.has_imu[i] = r.has_imu[i] and w.imu_ok[i]
        r.has_fix[i] = r.has_fix[i] and w.fix_ok[i]
    navigate(filters, w.dt_s[0], r.gyro, r.accel, r.has_imu, r.pos, r.quat, r.has_fix, w.acting)
    return finite


@njit(cache=True)
def no_peer_slots(n):
    """The peer slots' (wrench, age, valid, arm) of ``n`` robots while no message is ever sent
    (no estimators): zeros (n, n - 1, 6), (n, n - 1), (n, n - 1), (n, n - 1, 4)."""
    return (
        np.zeros((n, n - 1, 6)), np.zeros((n, n - 1)), np.zeros((n, n - 1)),
        np.zeros((n, n - 1, 4)),
    )  # fmt: skip


@njit(cache=True)
def sense_observe_and_reward(
    qpos, qvel, warnings, cvel, site_xpos, site_xmat, subtree_com, sensordata, period_s, normals,
    fix, world, readings, filters, obs, rewards, arms, xpos, xmat, robot_contacts,
    cargo_contacts, shapes, time_s,
):  # fmt: skip
    """``sense_and_navigate`` then ``observe_and_reward`` of the robots the record ``world``
    counts as acting, in one call (the arguments are theirs), for a step with nothing between
    them: no estimators (no peer message, no estimate, no information gained: zeros) and no
    release. Returns whether the state and the observations are finite."""
    finite = sense_and_navigate(
        qpos, qvel, warnings, cvel, site_xpos, site_xmat, subtree_com, sensordata, period_s,
        normals, fix, world, readings, filters,
    )  # fmt: skip
    n = obs.shape[0]
    return observe_and_reward(
        obs, rewards, world[0].acting, world, readings, filters, arms, xpos, xmat,
        no_peer_slots(n), np.zeros((n, 0)), np.zeros(n), robot_contacts, cargo_contacts, finite,
        shapes, time_s,
    )  # fmt: skip
