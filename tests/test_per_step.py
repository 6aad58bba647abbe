"""The estimator's compiled per-step path against its Python path, and the env's team estimation
(``envs.estimation``) against the messages it was given."""

from dataclasses import replace

import numpy as np
import pytest

from astrocargo.envs import astrobee_cargo_v0
from astrocargo.envs.world import World
from astrocargo.estimator import momentum, per_step
from astrocargo.estimator.cargo_estimator import CargoEstimator

DT = 1.0 / 62.5


def _readings(n_steps: int, seed: int = 3) -> list[tuple]:
    """Smooth, noisy readings of a moving robot, with a fix every 5th step and one bad sample."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps)[:, None] * DT
    accel = 0.01 * np.sin(0.7 * t + [0.0, 1.0, 2.0]) + 1e-3 * rng.normal(size=(n_steps, 3))
    gyro = 0.05 * np.sin(0.3 * t + [0.5, 1.5, 2.5]) + 2e-4 * rng.normal(size=(n_steps, 3))
    q = np.array([1.5, 0.0]) + 0.2 * np.sin(0.4 * t + [0.0, 1.0])
    thrust = 0.1 * np.sin(0.5 * t + np.arange(6))
    pos = 0.01 * t * [1.0, 0.5, 0.0]
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    accel[40 % n_steps, 1] = np.nan  # one non-finite sample: the Python path holds the last
    out = []
    for k in range(n_steps):
        fix = k % 5 == 0
        out.append((k, accel[k], gyro[k], q[k], thrust[k], pos[k] if fix else None,
                    quat if fix else None))  # fmt: skip
    return out


def _run(est: CargoEstimator, readings, as_lists: bool) -> list:
    messages = []
    for k, accel, gyro, q, thrust, pos, quat in readings:
        args = [accel, gyro, q, thrust, pos, quat]
        if as_lists:  # not float64 arrays: the compiled call refuses them, Python takes them
            args = [None if a is None else a.tolist() for a in args]
        messages.append(est.step(k, *args))
    return messages


def _assert_rounding_equal(a, b) -> None:
    """Equal up to rounding: the two paths take the same steps, but the Python path's products
    go through numpy's BLAS and the compiled one's through numba's (scipy's BLAS), whose kernels,
    chosen per CPU, may round differently in the last bit (a bit-equality test fails on some
    machines). A logic difference moves these values by many orders of magnitude more."""
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-13 * np.abs(b).max(initial=0.0))


def test_compiled_step_equals_python_path():
    robot = World(1).robot_model(0)
    readings = _readings(200)
    compiled = CargoEstimator(robot, 0, [], DT, warmup_s=0.5)
    python = CargoEstimator(robot, 0, [], DT, warmup_s=0.5)
    calls = []
    original = per_step.estimator_step

    def counted(*args):
        calls.append(1)
        return original(*args)

    per_step.estimator_step = counted
    try:
        got = _run(compiled, readings, as_lists=False)
        n_compiled = len(calls)
        expected = _run(python, readings, as_lists=True)
    finally:
        per_step.estimator_step = original
    assert n_compiled > 150  # the compiled call was made (and refused the lists)
    assert compiled.counters == python.counters
    assert compiled.counters["bad_readings"] == 1
    sent = [(a, b) for a, b in zip(got, expected, strict=True) if a is not None]
    assert len(sent) > 10
    for a, b in sent:
        _assert_rounding_equal(a.wrench_grasp, b.wrench_grasp)
        _assert_rounding_equal(a.wrench_world, b.wrench_world)
        _assert_rounding_equal(a.wrench_cov_grasp, b.wrench_cov_grasp)
        assert a.tainted == b.tainted and a.fix == b.fix
    _assert_rounding_equal(compiled.pre.filter.state, python.pre.filter.state)
    # The momentum form's chain (rate filter, products, product filter) took the same steps.
    _assert_rounding_equal(compiled.pre.rate_filter.state, python.pre.rate_filter.state)
    _assert_rounding_equal(compiled.pre.product_filter.state, python.pre.product_filter.state)
    assert np.abs(compiled.balance_filter.state[1]).max() > 0  # the derivative output is used
    _assert_rounding_equal(compiled.balance_filter.state, python.balance_filter.state)
    _assert_rounding_equal(compiled._rot_world_base, python._rot_world_base)


def test_compiled_step_takes_the_servo_ripple_off_like_python():
    """With the servo targets' rate given, the compiled call takes the ripple off between the
    map's refreshes (``estimator_step``'s ``with_ripple``); the Python path (readings as lists,
    which the compiled call refuses) takes it off in ``_without_servo_ripple``: the same steps."""
    robot = World(1).robot_model(0)
    readings = _readings(200)
    t = np.arange(len(readings))[:, None] * DT
    rates = 0.1 * np.sin(0.9 * t + [0.0, 2.0])
    rates[60:90] = 0.0  # at rest for a while: no ripple change, then it starts again
    compiled = CargoEstimator(robot, 0, [], DT, warmup_s=0.5)
    python = CargoEstimator(robot, 0, [], DT, warmup_s=0.5)
    with_ripple = []
    original = per_step.estimator_step

    def counted(*args):
        result = original(*args)  # a TypeError (the lists) propagates: not counted
        with_ripple.append(args[-1] and result[0] != per_step.NOT_USABLE)
        return result

    per_step.estimator_step = counted
    try:
        got, expected = [], []
        for (k, accel, gyro, q, thrust, pos, quat), rate in zip(readings, rates, strict=True):
            got.append(compiled.step(k, accel, gyro, q, thrust, pos, quat, servo_target_rate=rate))
            lists = [None if a is None else a.tolist() for a in (accel, gyro, q, thrust, pos, quat)]
            expected.append(python.step(k, *lists, servo_target_rate=rate.tolist()))
    finally:
        per_step.estimator_step = original
    assert sum(with_ripple) > 100  # the compiled call took the ripple off on most steps
    assert compiled.counters == python.counters
    np.testing.assert_array_equal(compiled._servo_ripple_prev, python._servo_ripple_prev)
    sent = [(a, b) for a, b in zip(got, expected, strict=True) if a is not None]
    assert len(sent) > 10
    for a, b in sent:
        _assert_rounding_equal(a.wrench_grasp, b.wrench_grasp)
    _assert_rounding_equal(compiled.pre.filter.state, python.pre.filter.state)
    _assert_rounding_equal(compiled.balance_filter.state, python.balance_filter.state)


def test_compiled_step_raises_on_bad_shape_like_python():
    est = CargoEstimator(World(1).robot_model(0), 0, [], DT)
    readings = _readings(50)
    _run(est, readings[:2], as_lists=False)
    k, accel, gyro, q, thrust, _, _ = readings[2]
    with pytest.raises(ValueError, match="joint_pos_rad"):
        est.step(k, accel, gyro, np.zeros(3), thrust)
    with pytest.raises(ValueError, match="stamps must increase"):
        est.step(1, accel, gyro, q, thrust)


def test_peer_slots_hold_the_latest_delivered_message():
    env = astrobee_cargo_v0.parallel_env(n_robots=3, noise="nominal")
    env.reset(seed=2)
    steps = 300  # past the estimators' warm-up: messages have been sent
    for _ in range(steps):
        env.step({a: np.zeros(8) for a in env.agents})
    sim = env.sim
    wrench, age, valid, arm = sim.estimation.peer_slot_values(np.ones(3, dtype=bool), steps)
    assert valid.all()
    for i in range(3):
        for p, j in enumerate(j for j in range(3) if j != i):
            msg = sim.peer_msgs[i][j]
            np.testing.assert_array_equal(wrench[i, p], msg.wrench_world)
            assert age[i, p] == pytest.approx((steps - msg.stamp) * sim.dt_s)
            np.testing.assert_array_equal(arm[i, p], sim.estimation.sent_arm[j][msg.stamp])
    sim.estimation.forget(0, 1)
    wrench, _, valid, _ = sim.estimation.peer_slot_values(np.array([True, True, False]), steps)
    assert valid[0].tolist() == [0.0, 1.0] and not valid[2].any() and not wrench[2].any()


def test_servo_ripple_is_taken_off_the_accelerometer_where_the_target_rate_changes():
    """The accelerometer's period mean holds the change of the IMU point's servo ripple between
    the period's ends (``momentum.servo_ripple``): nothing at rest or at a steady target rate,
    -R_BI^T v_r / dt where the rate starts and the opposite where it stops; nothing at all for a
    robot whose servo gain is unknown."""
    robot = World(1).robot_model(0)
    q, accel = np.array([1.5, 0.2]), np.array([1e-3, -2e-3, 3e-3])
    rates = [np.zeros(2), np.array([0.12, -0.12]), np.array([0.12, -0.12]), np.zeros(2)]
    est = CargoEstimator(robot, 0, [], DT)
    got = [est._without_servo_ripple(k, accel, q, rate) for k, rate in enumerate(rates, 1)]
    ripple = momentum.servo_ripple(robot, q, est.params_mean(), rates[1], DT)
    change = robot.imu_rot.T @ ripple / DT
    assert np.linalg.norm(change) > 1e-5  # m/s^2: the check can fail
    np.testing.assert_array_equal(got[0], accel)
    np.testing.assert_allclose(got[1], accel - change, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(got[2], accel)
    np.testing.assert_allclose(got[3], accel + change, rtol=1e-12, atol=0)
    blind = CargoEstimator(replace(robot, servo_gain=None), 0, [], DT)
    for rate in rates:
        np.testing.assert_array_equal(blind._without_servo_ripple(1, accel, q, rate), accel)
