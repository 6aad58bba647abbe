"""Sensors: readings describe the current state, ideal readings match the model, noise matches
the profile and is reproducible from the seed."""

import mujoco
import numpy as np
import pytest

from astrocargo.envs.sensors import NOISE_PROFILES, SensorSuite, noise_profile
from astrocargo.envs.world import World
from astrocargo.estimator import rne


def _moving_world(seconds: float = 1.0):
    world = World(1)
    data = world.make_data()
    h = world.robots[0]
    robot = world.robot_model(0)
    data.ctrl[list(h.thrust_actuators)] = 0.8 * robot.thrust_limit
    data.ctrl[list(h.arm_actuators)] = [-1.2, 0.4]
    mujoco.mj_step(world.model, data, nstep=int(seconds / world.model.opt.timestep))
    mujoco.mj_forward(world.model, data)
    return world, data


def test_ideal_imu_matches_model_kinematics():
    world, data = _moving_world()
    h, robot = world.robots[0], world.robot_model(0)
    packet = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0)).read(data, 0)[0]
    vel, acc = np.zeros(6), np.zeros(6)
    mujoco.mj_objectVelocity(world.model, data, mujoco.mjtObj.mjOBJ_XBODY, h.base_body, vel, 1)
    mujoco.mj_objectAcceleration(world.model, data, mujoco.mjtObj.mjOBJ_XBODY, h.base_body, acc, 1)
    w, wd, a = vel[:3], acc[:3], acc[3:]
    r = robot.imu_pos
    a_imu_base = a + np.cross(wd, r) + np.cross(w, np.cross(w, r))
    np.testing.assert_allclose(packet.accel_imu, robot.imu_rot.T @ a_imu_base, atol=1e-10)
    np.testing.assert_allclose(packet.gyro_imu, robot.imu_rot.T @ w, atol=1e-12)
    assert np.linalg.norm(a_imu_base) > 1e-3  # the robot really accelerates
    np.testing.assert_allclose(packet.joint_pos_rad, data.qpos[list(h.arm_qpos_adr)], atol=1e-12)
    # Readings describe the current state, not the one before the last step.
    np.testing.assert_allclose(packet.base_pos_world, data.xpos[h.base_body], atol=1e-12)
    np.testing.assert_allclose(packet.base_quat_world, data.xquat[h.base_body], atol=1e-12)


def test_nominal_noise_statistics_and_rate():
    world, data = _moving_world(0.1)
    profile = noise_profile("nominal")
    ideal = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0)).read(data, 0)[0]
    suite = SensorSuite(world, profile, np.random.default_rng(1))
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
    world, data = _moving_world(0.1)
    a = SensorSuite(world, noise_profile("nominal"), np.random.default_rng(5)).read(data, 3)[0]
    b = SensorSuite(world, noise_profile("nominal"), np.random.default_rng(5)).read(data, 3)[0]
    c = SensorSuite(world, noise_profile("nominal"), np.random.default_rng(6)).read(data, 3)[0]
    np.testing.assert_array_equal(a.accel_imu, b.accel_imu)
    assert not np.array_equal(a.accel_imu, c.accel_imu)


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


def test_unknown_profile():
    with pytest.raises(ValueError, match="allowed"):
        noise_profile("perfect")


def test_rne_kinematics_match_imu_through_lever_arm():
    """The base origin acceleration recovered from the IMU through the lever arm."""
    world, data = _moving_world()
    robot = world.robot_model(0)
    h = world.robots[0]
    packet = SensorSuite(world, noise_profile("ideal"), np.random.default_rng(0)).read(data, 0)[0]
    acc = np.zeros(6)
    mujoco.mj_objectAcceleration(world.model, data, mujoco.mjtObj.mjOBJ_XBODY, h.base_body, acc, 1)
    w = robot.imu_rot @ packet.gyro_imu
    wd = acc[:3]
    a_origin = (
        robot.imu_rot @ packet.accel_imu
        - np.cross(wd, robot.imu_pos)
        - np.cross(w, np.cross(w, robot.imu_pos))
    )
    np.testing.assert_allclose(a_origin, acc[3:], atol=1e-10)
    kin = rne.propagate(robot, w, wd, a_origin, packet.joint_pos_rad, np.zeros(2), np.zeros(2))
    assert np.all(np.isfinite(kin.grasp_pos))
