"""The record side of an update instant in one compiled call (``estimator.instant_kernels``)
against its pieces: ``NoiseModel.instant_modes`` equals ``momentum_jacobians`` then
``message_modes``; the ring of pre-filter states equals the deque it replaced."""

import bisect
import collections
import copy
import operator

import numpy as np
import pytest

from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.momentum import rate_square_terms
from astrocargo.estimator.team_noise import message_map

DT = 0.016


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def _model():
    return CargoEstimator(_robot(), 0, [1], DT, sensor_noise=(1e-3, 2e-4, 1e-3)).noise


def _pre_state(rng, nj: int) -> np.ndarray:
    state = 0.1 * rng.normal(size=(3, 12 + nj))
    state[0, 6 : 6 + nj] += np.linspace(0.3, -0.5, nj)
    return state


@pytest.mark.parametrize("with_rate", [False, True])
def test_instant_modes_equal_the_jacobians_then_the_message_modes(with_rate):
    """Over 20 instants (3 factor refreshes, a gap in the stamps), the one call gives the same
    modes, bit for bit, as ``momentum_jacobians`` on a twin (the same delayed state,
    autocorrelation and factors), and the message factor of ``message_modes``, F F^T = M M^T
    (M the scaled map, ``team_noise.message_map``)."""
    robot = _robot()
    model = CargoEstimator(robot, 0, [1], DT, sensor_noise=(1e-3, 2e-4, 1e-3)).noise
    assert model.update_every == 10
    twin = copy.deepcopy(model)
    rng = np.random.default_rng(3)
    nj = model._n_joints
    stamps = [10 * k for k in range(1, 12)] + [10 * k for k in range(15, 24)]
    for stamp in stamps:
        pre_state, regressor = _pre_state(rng, nj), rng.normal(size=(6, 10))
        rate = None
        if with_rate:
            terms, weights = rate_square_terms(robot, pre_state[0, 6 : 6 + nj])
            rate = (terms, 3e-5 * weights)
        jac, (f_links, f_grasp, ones) = model.instant_modes(stamp, regressor, pre_state, rate)
        links, y = jac
        links_t, y_t = twin.momentum_jacobians(stamp, regressor, pre_state, rate)
        np.testing.assert_array_equal(links, links_t)
        np.testing.assert_array_equal(y, y_t)
        f = np.vstack((f_links, f_grasp))
        m = message_map(links, y, model._mode_std)
        cov = m @ m.T
        atol = 1e-12 * np.abs(cov).max()
        np.testing.assert_allclose(f @ f.T, cov, rtol=1e-12, atol=atol)
        np.testing.assert_array_equal(f, np.vstack(twin.message_modes(links_t, y_t)[:2]))
        np.testing.assert_array_equal(ones, np.ones(9))
    np.testing.assert_array_equal(model._held_factor, twin._held_factor)
    for name in ("_cross", "_power", "_ring", "_ring_power", "_ring_index"):
        a, b = getattr(model.autocorrelation, name), getattr(twin.autocorrelation, name)
        np.testing.assert_array_equal(a, b)


def _deque_delayed_motion(states, stamp, pre_state, lag_steps, update_every, dt_s):
    """The delayed motion as it was (a deque of (stamp, state) and a bisection), for reference."""
    target = stamp - lag_steps
    while states and states[0][0] < target - 2 * update_every:
        states.popleft()
    states.append((int(stamp), np.array(pre_state[:3], dtype=float)))
    i = bisect.bisect_left(states, target, key=operator.itemgetter(0))
    if i == len(states) or (i > 0 and target - states[i - 1][0] <= states[i][0] - target):
        i -= 1
    s, x = states[i]
    moved = x.copy()
    moved[:2] -= (s - target) * dt_s * x[1:3]
    return moved


@pytest.mark.parametrize("lag_steps", [0.0, 15.0, 37.5, 140.0])
def test_the_ring_of_states_gives_the_deque_s_delayed_motion(lag_steps):
    """The ring (``instant_kernels.keep_motion``, ``nearest_motion``) picks the state the deque
    picked (ties to the earlier, drops older than 2 updates before the target), across a gap,
    a tie and the ring's growth (a long lag keeps more than its first 8 slots)."""
    model = _model()
    model._jacobian_lag_steps = lag_steps
    states = collections.deque()
    rng = np.random.default_rng(5)
    nj = model._n_joints
    stamps = [10 * k for k in range(1, 30)] + [10 * k for k in range(33, 60)] + [605, 610]
    for stamp in stamps:
        pre_state = _pre_state(rng, nj)
        got = model._delayed_motion(stamp, pre_state)
        expected = _deque_delayed_motion(states, stamp, pre_state, lag_steps, 10, DT)
        np.testing.assert_array_equal(got, expected)
        assert model._motion_ring[2][1] == len(states)
    assert (model._motion_ring[0].shape[0] > 8) == (lag_steps > 60)


def test_a_full_ring_raises_instead_of_overwriting():
    from astrocargo.estimator.instant_kernels import keep_motion

    stamps, states, span = np.zeros(2, np.int64), np.zeros((2, 3, 4)), np.zeros(2, np.int64)
    pre_state = np.ones((3, 4))
    keep_motion(stamps, states, span, 10, pre_state, 0.0)
    keep_motion(stamps, states, span, 20, pre_state, 0.0)
    with pytest.raises(ValueError, match="full"):
        keep_motion(stamps, states, span, 30, pre_state, 0.0)
    keep_motion(stamps, states, span, 30, pre_state, 15.0)  # the oldest dropped: room again
    np.testing.assert_array_equal(span, [1, 2])


@pytest.mark.parametrize("over_time_window", [0, 24])
def test_rate_square_terms_made_in_the_call_equal_those_given(over_time_window):
    """``instant_modes`` with ``rate_at`` (the joint angles and the scale: the terms made in the
    call, ``instant_kernels.record_instant``) gives the modes and message factor, bit for bit,
    of the same call given ``momentum.rate_square_terms`` and the scaled weights; over time too
    (``momentum_jacobians``)."""
    robot = _robot()
    model = CargoEstimator(
        robot, 0, [1], DT, sensor_noise=(1e-3, 2e-4, 1e-3), over_time_window=over_time_window
    ).noise
    twin = copy.deepcopy(model)
    rng = np.random.default_rng(4)
    nj = model._n_joints
    for stamp in range(10, 200, 10):
        pre_state, regressor = _pre_state(rng, nj), rng.normal(size=(6, 10))
        q = pre_state[0, 6 : 6 + nj]
        terms, weights = rate_square_terms(robot, q)
        got = model.instant_modes(stamp, regressor, pre_state, rate_at=(q, 3e-5))
        expected = twin.instant_modes(stamp, regressor, pre_state, (terms, 3e-5 * weights))
        for a, b in zip((*got[0], *got[1]), (*expected[0], *expected[1]), strict=True):
            np.testing.assert_array_equal(a, b)
    assert np.any(got[0][0][:, -terms.shape[0] :])  # the terms' modes are there


@pytest.mark.parametrize("kinds", ["gggaaa", "ggaagg", "gagaga"])
def test_held_channels_that_share_a_factor_take_the_products_of_each_alone(kinds):
    """``chain_modes._noise_modes_into`` multiplies each run of held channels with one factor in
    one product; every mode equals, bit for bit, that channel's product alone."""
    from astrocargo.estimator.chain_modes import (
        _factored_into,
        _noise_modes_into,
        _readout_columns,
    )
    from astrocargo.estimator.momentum import CARGO_P_MAP, CARGO_Q_MAP

    rng = np.random.default_rng(8)
    nj = 2
    jacs = rng.normal(size=(2, 33, 6 + 2 * nj)) * 10.0 ** rng.uniform(-6, 2, size=(2, 33, 1))
    gyro, accel, point = rng.normal(size=(4, 4)), rng.normal(size=(4, 4)), rng.normal(size=(8, 8))
    factors = np.ascontiguousarray(np.stack([gyro if k == "g" else accel for k in kinds]))
    n = 24 + 8 * nj
    links, y = np.zeros((6, n)), np.zeros((n, 60))
    _noise_modes_into(links, y, jacs, nj, factors, point, CARGO_P_MAP, CARGO_Q_MAP)
    ref_links, ref_y = links.copy(), y.copy()
    ref_links[:, :24], ref_y[:24] = np.nan, np.nan
    readout = _readout_columns(jacs, CARGO_P_MAP, CARGO_Q_MAP)
    for c in range(6):
        columns = np.stack([np.full(4, c), np.arange(4)], axis=1)[None].astype(np.int64)
        _factored_into(ref_links, ref_y, np.array([4 * c]), readout, columns, factors[c])
    np.testing.assert_array_equal(links, ref_links)
    np.testing.assert_array_equal(y, ref_y)


def test_message_pose_and_servo_ripple_from_the_robot_record_equal_their_python_forms():
    """``message_pose`` (the grasp pose at the encoders' angles, then in world axes, and the
    wrench turned into world axes) and ``servo_ripple_of`` equal, bit for bit,
    ``rne.grasp_pose`` with numpy's products and ``momentum.servo_ripple_velocities``, from
    one record of the robot (``robot_record``)."""
    from astrocargo.estimator.geometry import quat_to_mat
    from astrocargo.estimator.instant_kernels import message_pose, robot_record, servo_ripple_of
    from astrocargo.estimator.momentum import servo_ripple_velocities
    from astrocargo.estimator.rne import grasp_pose

    robot = _robot()
    assert robot.servo_gain is not None
    record = robot_record(robot)
    rng = np.random.default_rng(9)
    cargo = np.array([2.0, 0.1, -0.05, 0.2, 0.3, 0.25, 0.2, 0.01, -0.02, 0.005])
    for _ in range(20):
        q = rng.uniform(-1.5, 1.5, robot.n_joints)
        rot_wb = np.ascontiguousarray(quat_to_mat(rng.normal(size=4) + [2.0, 0.0, 0.0, 0.0]))
        pos_wb, wrench = rng.normal(size=3), rng.normal(size=6) * [1, 1, 1, 0.1, 0.1, 0.1]
        rot_wg, pos_wg, wrench_world = message_pose(record, q, rot_wb, pos_wb, wrench)
        rot_bg, pos_bg = grasp_pose(robot, q)
        turn = np.zeros((6, 6))
        turn[:3, :3] = turn[3:, 3:] = rot_wb @ rot_bg
        np.testing.assert_array_equal(rot_wg, rot_wb @ rot_bg)
        np.testing.assert_array_equal(pos_wg, pos_wb + rot_wb @ pos_bg)
        np.testing.assert_array_equal(wrench_world, turn @ wrench)
        np.testing.assert_array_equal(
            servo_ripple_of(record, q, cargo, 0.016),
            servo_ripple_velocities(robot, q, cargo, 0.016),
        )
