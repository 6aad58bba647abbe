"""The record side of an update instant in one compiled call (``record_modes``).

At each update instant a robot records its balance's sensor-noise modes in the momentum chain
and the 9 modes its message carries (``NoiseModel.momentum_jacobians``,
``NoiseModel.message_modes``). The pieces (the delayed pre-filter state, the regressor's
autocorrelation sums, the modes and the message's map M) are compiled here into one call over
the persistent state kept in preallocated arrays:
- the ring of recorded pre-filter states (``keep_motion``, ``nearest_motion``): stamps (K,),
  states (K, 3, 12 + nj), span [first slot, count] (2,);
- the autocorrelation's sums and ring (``motion.RegressorAutocorrelation``), in place.
``record_instant`` is that call with the robot's constants as one record (``record_constants``:
numba checks and unboxes each argument of a call, a record at once) and the encoders' squared
rate noise's terms (``momentum.rate_square_terms``) computed inside it. Two more calls of an
instant take the robot's constants as one record (``robot_record``): the message's grasp pose
and wrench in world axes (``message_pose``) and the servos' ripple map (``servo_ripple_of``).
The arithmetic is the same as the pieces' one by one, bit for bit, the message's factor
F F^T = M M^T included (``team_noise.message_factor``, as in ``NoiseModel.message_modes``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .chain_modes import instant_noise_modes
from .momentum import _rate_square_terms, servo_ripple_map
from .motion import _add_regressor
from .records import record_of
from .rne import RobotArrays, RobotDescription, grasp_pose_into
from .team_noise import message_factor


@njit(cache=True)
def keep_motion(stamps, states, span, stamp, pre_state, horizon):
    """Into the ring (``stamps`` (K,), ``states`` (K, 3, w), ``span`` [first, count], increasing
    stamps): drop the oldest states while their stamp is below ``horizon`` (steps), then append
    ``pre_state``[:3] recorded at ``stamp``. The caller leaves room for one (count < K):
    ValueError if there is none."""
    size = stamps.shape[0]
    first, count = span[0], span[1]
    while count > 0 and stamps[first] < horizon:
        first = (first + 1) % size
        count -= 1
    if count == size:
        raise ValueError("the ring of states is full")
    slot = (first + count) % size
    stamps[slot] = stamp
    states[slot] = pre_state[:3]
    span[0], span[1] = first, count + 1


@njit(cache=True)
def nearest_motion(stamps, states, span, target, dt_s):
    """The ring's state (value, derivative, second derivative) (3, w) recorded nearest ``target``
    (steps; of two as near, the earlier), moved the rest of the way along its derivatives (first
    order, ``dt_s`` s per step): x[:2] - (s - target) dt x[1:3]."""
    size = stamps.shape[0]
    first, count = span[0], span[1]
    i = 0  # the first recorded at or after the target (bisect_left)
    while i < count and stamps[(first + i) % size] < target:
        i += 1
    if i == count or (
        i > 0 and target - stamps[(first + i - 1) % size] <= stamps[(first + i) % size] - target
    ):
        i -= 1
    slot = (first + i) % size
    x = states[slot]
    back = (stamps[slot] - target) * dt_s
    moved = x.copy()
    moved[:2] -= back * x[1:3]
    return moved


@njit(cache=True)
def record_modes(arrays, imu_pos, n_joints, step_s, factors, point_factor, rate_terms, rate_var,
                 n_rate, mode_std, motion_ring, autocorrelation, stamp, pre_state, target,
                 horizon, dt_s, index, regressor, add):  # fmt: skip
    """An update instant's modes and its message's, in one call:
    1. the pre-filter's ``pre_state`` kept in ``motion_ring`` (stamps, states, span), drops
       below ``horizon`` (``keep_motion``), and x the state near ``target``
       (``nearest_motion``);
    2. with ``add``, the ``regressor`` (6, 10) of update ``index`` into the autocorrelation's
       sums (cross, power, ring, ring_power, ring_index) (``motion._add_regressor``);
    3. the modes d links - d thrust (6, n), d Y (n, 6, 10) at x
       (``chain_modes.instant_noise_modes``, with the channels' ``factors`` (6, 4, 4) and
       ``point_factor`` (8, 8));
    4. the message's factor F (9, 9), F F^T = M M^T, M = ``team_noise.message_map`` (9, n)
       of the modes scaled by ``mode_std`` (``team_noise.message_factor``).
    Returns (d links, d Y, F)."""
    stamps, states, span = motion_ring
    keep_motion(stamps, states, span, stamp, pre_state, horizon)
    x = nearest_motion(stamps, states, span, target, dt_s)
    if add:
        cross, power, ring, ring_power, ring_index = autocorrelation
        _add_regressor(cross, power, ring, ring_power, ring_index, index, regressor)
    links, y = instant_noise_modes(arrays, imu_pos, x, n_joints, step_s, factors, point_factor,
                                   rate_terms, rate_var, n_rate)  # fmt: skip
    return links, y, message_factor(links, y, mode_std)


def robot_record(robot: RobotDescription) -> np.ndarray:
    """The robot's constants as one record (``records.record_of``): its ``arrays`` by their
    names (``grasp_link`` an array of one), ``imu_pos`` (3,) m in B and ``servo_gain``
    (n_joints,) N m/rad (zeros when unknown), for ``message_pose`` and ``servo_ripple_of``."""
    fields = {name: np.atleast_1d(value) for name, value in robot.arrays._asdict().items()}
    gain = np.zeros(robot.n_joints) if robot.servo_gain is None else robot.servo_gain
    fields.update(
        imu_pos=np.asarray(robot.imu_pos, dtype=float),
        servo_gain=np.asarray(gain, dtype=float),
    )
    return record_of(fields)


@njit(cache=True)
def servo_ripple_of(robot, q, cargo, dt_s):
    """``momentum.servo_ripple_velocities`` from the robot's record ``robot``
    (``robot_record``, its servos' gains known): ``momentum.servo_ripple_map`` at joint angles
    ``q`` rad and the cargo ``cargo`` (10,), times the gains and the period ``dt_s`` s
    (3, n_joints) m/s per rad/s."""
    c = robot[0]
    arrays = RobotArrays(
        c.parent[:], c.joint_axis[:], c.rot_in_parent[:], c.pos_in_parent[:], c.mass[:],
        c.com[:], c.inertia_com[:], c.grasp_link[0], c.grasp_rot[:], c.grasp_pos[:],
    )  # fmt: skip
    return servo_ripple_map(arrays, c.imu_pos[:], q, cargo, dt_s) * (c.servo_gain[:] * dt_s)


def record_constants(arrays: RobotArrays, imu_pos, point_factor, mode_std, n_joints: int,
                     n_rate: int, step_s: float, dt_s: float) -> np.ndarray:  # fmt: skip
    """``record_modes``' constant arguments as one record (``records.record_of``) for
    ``record_instant``: the robot's ``arrays`` by their names, ``imu_pos``, ``point_factor``,
    ``mode_std``, ``counts`` = (n_joints, n_rate) and ``times`` = (step_s, dt_s) s."""
    fields = {name: np.atleast_1d(value) for name, value in arrays._asdict().items()}
    fields.update(
        imu_pos=np.asarray(imu_pos, dtype=float),
        point_factor=np.asarray(point_factor, dtype=float),
        mode_std=np.asarray(mode_std, dtype=float),
        counts=np.array([n_joints, n_rate], dtype=np.int64),
        times=np.array([step_s, dt_s], dtype=float),
    )
    return record_of(fields)


@njit(cache=True)
def message_pose(robot, q, rot_world_base, pos_world_base, wrench_grasp):
    """What an instant's message says of the robot's grasp in world axes, from the robot's
    record ``robot`` (``robot_record``), its joint angles ``q`` (n_joints,) rad and the base's
    attitude R_WB and position p_WB (m): G's pose in B (``rne.grasp_pose_into``), then
    R_WG = R_WB R_BG, p_WG = p_WB + R_WB p_BG and the wrench W_G (6,) in world axes,
    diag(R_WG, R_WG) W_G (the products as numpy's, 3x3 and 6x6). Returns (R_WG, p_WG, W_W)."""
    c = robot[0]
    n_links = c.parent.shape[0]
    rot_bg, pos_bg = np.empty((3, 3)), np.empty(3)
    grasp_pose_into(
        rot_bg, pos_bg, np.empty((n_links + 1, 3, 3)), np.empty((n_links, 3)),
        np.empty((n_links + 1, 3)), c.parent[:], c.joint_axis[:], c.rot_in_parent[:],
        c.pos_in_parent[:], c.grasp_link[0], c.grasp_rot[:], c.grasp_pos[:], q,
    )  # fmt: skip
    rot_wg = rot_world_base @ rot_bg
    pos_wg = pos_world_base + rot_world_base @ pos_bg
    rot_world = np.zeros((6, 6))
    rot_world[:3, :3] = rot_wg
    rot_world[3:, 3:] = rot_wg
    return rot_wg, pos_wg, rot_world @ wrench_grasp


@njit(cache=True)
def record_instant(constants, factors, rate_terms, rate_var, rate_q, rate_scale, motion_ring,
                   autocorrelation, stamp, pre_state, target, horizon, index, regressor,
                   add):  # fmt: skip
    """``record_modes`` with its constants from ``constants`` (``record_constants``). The
    squared rate noise's terms: ``rate_terms`` (k, ``SIZE``) with variances ``rate_var`` (k,)
    as given or, with joint angles ``rate_q`` (n_joints,) rad (empty: none), computed here,
    ``momentum.rate_square_terms`` at ``rate_q`` with variances ``rate_scale`` w_k (w_k 2 for a
    square, 1 for a product of two joints). Returns (d links, d Y, F) as ``record_modes``."""
    c = constants[0]
    fields = (
        c.parent[:], c.joint_axis[:], c.rot_in_parent[:], c.pos_in_parent[:], c.mass[:],
        c.com[:], c.inertia_com[:], c.grasp_link[0], c.grasp_rot[:], c.grasp_pos[:],
    )  # fmt: skip
    arrays = RobotArrays(*fields)
    imu_pos, n_joints, n_rate = c.imu_pos[:], c.counts[0], c.counts[1]
    if rate_q.shape[0] != 0 and n_rate != 0:
        rate_terms = _rate_square_terms(*fields, imu_pos, rate_q)
        weights = np.ones(rate_terms.shape[0])
        weights[:n_joints] = 2.0
        rate_var = rate_scale * weights
    return record_modes(arrays, imu_pos, n_joints, c.times[0], factors, c.point_factor[:],
                        rate_terms, rate_var, n_rate, c.mode_std[:], motion_ring,
                        autocorrelation, stamp, pre_state, target, horizon, c.times[1], index,
                        regressor, add)  # fmt: skip
