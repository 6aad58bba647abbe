"""Sensors: readings describe the current state, ideal readings match the model, noise matches
the profile and is reproducible from the seed."""

import mujoco
import numpy as np
import pytest

from astrocargo.envs.sensors import NOISE_PROFILES, NormalStream, SensorSuite, noise_profile
from astrocargo.envs.world import World

CONTROL_PERIOD_S = 0.016


def _moving_world(seconds: float = 1.0, suites=()):
    """Drive a robot, then run one more control period bracketed by ``begin_period``."""
    world = World(1)
    data = world.make_data()
    h = world.robots[0]
    robot = world.robot_model(0)
    data.ctrl[list(h.thrust_actuators)] = 0.8 * robot.thrust_limit
    data.ctrl[list(h.arm_actuators)] = [-1.2, 0.4]
    mujoco.mj_step(world.model, data, nstep=int(seconds / world.model.opt.timestep))
    mujoco.mj_forward(world.model, data)
    for suite in suites:
        suite.begin_period(data)
    mujoco.mj_step(world.model, data, nstep=round(CONTROL_PERIOD_S / world.model.opt.timestep))
    mujoco.mj_forward(world.model, data)
    return world, data


def _suite(profile: str, seed: int = 0, world=None):
    return SensorSuite(world or World(1), noise_profile(profile), np.random.default_rng(seed))


def test_ideal_imu_is_the_period_mean():
    """The ideal IMU reports the mean specific force and rate over the control period: compare
    with MuJoCo's own accelerometer and gyro sensors averaged over the period's physics steps."""
    world = World(1)
    data = world.make_data()
    h = world.robots[0]
    robot = world.robot_model(0)
    suite = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0))
    data.ctrl[list(h.thrust_actuators)] = 0.8 * robot.thrust_limit
    data.ctrl[list(h.arm_actuators)] = [-1.2, 0.4]
    mujoco.mj_step(world.model, data, nstep=250)
    mujoco.mj_forward(world.model, data)
    suite.begin_period(data)
    acc_world, gyro_world = [], []
    n = round(CONTROL_PERIOD_S / world.model.opt.timestep)
    for k in range(4 * n + 1):  # fine sampling: step at a quarter of the physics step
        if k:
            world.model.opt.timestep /= 4
            mujoco.mj_step(world.model, data)
            world.model.opt.timestep *= 4
            mujoco.mj_forward(world.model, data)
        rot = data.site_xmat[h.imu_site].reshape(3, 3)
        if k == 2 * n:
            rot_mid = rot.copy()
        adr = h.sensor_adr
        w = 0.5 if k in (0, 4 * n) else 1.0  # trapezoid rule
        acc_world.append(w * rot @ data.sensordata[adr["imu_accel"] : adr["imu_accel"] + 3])
        gyro_world.append(w * rot @ data.sensordata[adr["imu_gyro"] : adr["imu_gyro"] + 3])
    packet = suite.read(data, 0)[0]
    mean_acc = np.sum(acc_world, axis=0) / (4 * n)
    mean_gyro = np.sum(gyro_world, axis=0) / (4 * n)
    # The reading is in the mid-period IMU frame.
    np.testing.assert_allclose(
        rot_mid @ packet.accel_imu, mean_acc, rtol=0, atol=1e-4 * np.linalg.norm(mean_acc) + 1e-7
    )
    np.testing.assert_allclose(
        rot_mid @ packet.gyro_imu, mean_gyro, rtol=0, atol=1e-3 * np.linalg.norm(mean_gyro) + 1e-9
    )
    assert np.linalg.norm(mean_acc) > 1e-3  # the robot really accelerates
    np.testing.assert_allclose(packet.joint_pos_rad, data.qpos[list(h.arm_qpos_adr)], atol=1e-12)
    # Localization describes the current state, not the one before the last step.
    np.testing.assert_allclose(packet.base_pos_world, data.xpos[h.base_body], atol=1e-12)
    np.testing.assert_allclose(packet.base_quat_world, data.xquat[h.base_body], atol=1e-12)


def test_read_without_begin_period_raises():
    world = World(1)
    data = world.make_data()
    with pytest.raises(ValueError, match="begin_period"):
        SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0)).read(data, 0)


def test_nominal_noise_statistics_and_rate():
    world = World(1)
    profile = noise_profile("nominal")
    ideal_suite = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0))
    suite = SensorSuite(world, profile, np.random.default_rng(1))
    world, data = _moving_world(0.1, (ideal_suite, suite))
    ideal = ideal_suite.read(data, 0)[0]
    n = 4000
    packets = [suite.read(data, k)[0] for k in range(n)]
    accel = np.array([p.accel_imu for p in packets]) - ideal.accel_imu
    gyro = np.array([p.gyro_imu for p in packets]) - ideal.gyro_imu
    joints = np.array([p.joint_pos_rad for p in packets]) - ideal.joint_pos_rad
    np.testing.assert_allclose(accel.std(axis=0), profile.accel_std, rtol=0.1)
    np.testing.assert_allclose(gyro.std(axis=0), profile.gyro_std, rtol=0.1)
    np.testing.assert_allclose(joints.std(axis=0), profile.encoder_std_rad, rtol=0.1)
    fixes = [k for k, p in enumerate(packets) if p.base_pos_world is not None]
    assert fixes == list(range(0, n, profile.localization_every))
    pos = np.array([packets[k].base_pos_world for k in fixes]) - ideal.base_pos_world
    np.testing.assert_allclose(pos.std(axis=0), profile.position_std_m, rtol=0.25)


def test_noise_is_seeded():
    world = World(1)
    suites = [
        SensorSuite(world, noise_profile("nominal"), np.random.default_rng(k)) for k in (5, 5, 6)
    ]
    world, data = _moving_world(0.1, suites)
    a, b, c = (suite.read(data, 3)[0] for suite in suites)
    np.testing.assert_array_equal(a.accel_imu, b.accel_imu)
    assert not np.array_equal(a.accel_imu, c.accel_imu)


@pytest.mark.parametrize("step", [1, 0])  # without and with a localization fix
def test_noise_is_drawn_robot_by_robot_in_reading_order(step):
    """Two robots read with nominal noise differ from the ideal readings by the standard
    deviations times one stream of normals: per robot accel (3), gyro (3), encoders (2), then at
    a fix position (3) and attitude (3)."""
    world = World(2)
    data = world.make_data()
    for h in world.robots:
        data.ctrl[list(h.thrust_actuators)] = 0.5 * world.robot_model(h.index).thrust_limit
    mujoco.mj_step(world.model, data, nstep=10)
    mujoco.mj_forward(world.model, data)
    profile = noise_profile("nominal")
    ideal_suite = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0))
    suite = SensorSuite(world, profile, np.random.default_rng(9))
    for s in (ideal_suite, suite):
        s.begin_period(data)
    mujoco.mj_step(world.model, data)
    mujoco.mj_forward(world.model, data)
    ideal, noisy = ideal_suite.read(data, step), suite.read(data, step)
    draws = np.random.default_rng(9).standard_normal(28 if step == 0 else 16).reshape(2, -1)
    for k in range(2):
        z = draws[k]
        np.testing.assert_allclose(noisy[k].accel_imu - ideal[k].accel_imu, 1e-3 * z[0:3])
        np.testing.assert_allclose(noisy[k].gyro_imu - ideal[k].gyro_imu, 2e-4 * z[3:6])
        assert np.abs(noisy[k].accel_imu).max() > 1e-3  # a real reading, not noise alone
        np.testing.assert_allclose(
            noisy[k].joint_pos_rad - ideal[k].joint_pos_rad, profile.encoder_std_rad * z[6:8]
        )
        if step == 0:
            np.testing.assert_allclose(
                noisy[k].base_pos_world - ideal[k].base_pos_world, profile.position_std_m * z[8:11]
            )


def test_actuation_noise():
    world = World(1)
    profile = noise_profile("nominal")
    suite = SensorSuite(world, profile, np.random.default_rng(2))
    command = np.array([0.3, -0.1, 0.0, 0.02, 0.0, -0.01])
    delivered = np.array([suite.actuate(command) for _ in range(5000)])
    expected = np.concatenate(
        (
            profile.force_std_n + profile.force_rel * np.abs(command[:3]),
            profile.torque_std_nm + profile.torque_rel * np.abs(command[3:]),
        )
    )
    np.testing.assert_allclose(delivered.std(axis=0), expected, rtol=0.1)
    np.testing.assert_allclose(
        delivered.mean(axis=0), command, atol=float(4 * expected.max() / np.sqrt(5000))
    )
    ideal = SensorSuite(world, NOISE_PROFILES["ideal"], np.random.default_rng(2))
    np.testing.assert_array_equal(ideal.actuate(command), command)


def test_normal_stream_hands_out_the_generator_stream_in_order():
    """Requests of any size, across block ends and larger than a block, get the numbers that
    drawing each request from the generator gives; a view handed out never changes later."""
    stream = NormalStream(np.random.default_rng(4), block=16)
    direct = np.random.default_rng(4)
    kept = []
    for n in [3, 5, 7, 1, 0, 16, 40, 2, 9, 9, 9, 33]:
        taken = stream.take(n)
        np.testing.assert_array_equal(taken, direct.standard_normal(n))
        kept.append((taken, taken.copy()))
    for taken, copy in kept:
        np.testing.assert_array_equal(taken, copy)


def test_unknown_profile():
    with pytest.raises(ValueError, match="allowed"):
        noise_profile("perfect")
