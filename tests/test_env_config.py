"""The env's one configuration (envs/config.py) and the compiled per-robot kernels behind the
observations and the navigation filter, against their textbook forms written plainly here."""

from __future__ import annotations

import copy
import dataclasses
import pickle
import re

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from astrocargo.envs import cargo_transport
from astrocargo.envs.cargo_transport import AstrobeeCargoEnv, EnvConfig, observation_layout
from astrocargo.envs.navigation import BaseNavigator
from astrocargo.envs.observations import OWN_BLOCKS, PEER_BLOCKS
from astrocargo.envs.sensors import SensorReadings, noise_profile
from astrocargo.envs.transport import CargoTransport
from astrocargo.envs.world import World
from astrocargo.estimator.rne import grasp_pose

SMALL = {"n_robots": 2, "control_hz": 12.5, "max_cycles": 20}


def test_arguments_table_mirrors_the_config():
    doc = cargo_transport.__doc__
    table = doc[doc.index("## Arguments") : doc.index("## Version History")]
    names = re.findall(r"^\| `(\w+)`", table, flags=re.MULTILINE)
    assert names == [f.name for f in dataclasses.fields(EnvConfig)]
    defaults = {f.name: f.default for f in dataclasses.fields(EnvConfig)}
    assert defaults["n_robots"] == 2 and defaults["noise"] == "nominal"


def test_config_or_keywords_build_the_same_env():
    config = EnvConfig(**SMALL, estimators=False, observe_estimates=False)
    by_config = AstrobeeCargoEnv(config)
    by_kwargs = AstrobeeCargoEnv(**SMALL, estimators=False, observe_estimates=False)
    assert by_config.config == by_kwargs.config
    obs_a, _ = by_config.reset(seed=3)
    obs_b, _ = by_kwargs.reset(seed=3)
    for agent in obs_a:
        assert np.array_equal(obs_a[agent], obs_b[agent])
    assert isinstance(by_config.sim, CargoTransport) and by_config.sim.config is config
    with pytest.raises(ValueError, match="either an EnvConfig or keyword"):
        AstrobeeCargoEnv(config, n_robots=3)
    with pytest.raises(TypeError, match="n_robot"):
        AstrobeeCargoEnv(n_robot=2)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_robots": 9}, "n_robots"),
        ({"control_hz": 5.0}, "control_hz"),
        ({"w_info": float("nan")}, "w_info"),
        ({"comm_noise": (0.1, -1.0)}, "comm_noise"),
        ({"max_cycles": 0}, "max_cycles"),
        ({"render_width": 2000}, "render_width"),
        ({"render_mode": "video"}, "render_mode"),
        ({"faults": [{"kind": "imu_dropout", "robot": 5, "start_s": 1, "duration_s": 1}]}, "robot"),
    ],
)
def test_config_checks_each_argument_once(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EnvConfig(**kwargs)


def test_config_normalises_and_replaces():
    config = EnvConfig(comm_noise=[0.1, 0.01], control_hz=25, faults=[])
    assert config.comm_noise == (0.1, 0.01) and isinstance(config.control_hz, float)
    assert config.faults == ()
    assert config.replace(n_robots=3).n_robots == 3
    with pytest.raises(ValueError, match="n_robots"):
        config.replace(n_robots=0)


def test_layout_is_built_from_the_block_tables():
    layout = observation_layout(3, observe_estimates=True)
    own = sum(size for _, size in OWN_BLOCKS)
    peer = sum(size for _, size in PEER_BLOCKS)
    assert layout["all"].stop == own + 2 * peer + 20
    assert [name for name, _ in OWN_BLOCKS] == list(layout)[: len(OWN_BLOCKS)]
    assert layout["peer1_valid"] == slice(own + peer + 7, own + peer + 8)
    assert layout["peer1_joint_vel"] == slice(own + 2 * peer - 2, own + 2 * peer)


KINEMATICS_TOL = 1e-12  # poses composed without approximation, in another order than MuJoCo's


@pytest.mark.parametrize("q", [(0.0, 0.0), (-1.2, 0.4), (-np.pi / 2, -0.7)])
def test_grasp_pose_is_mujocos_grasp_site_pose(q):
    """The one forward kinematics (rne.grasp_pose_into, which the observation kernels call)
    puts the grasp frame where MuJoCo puts the grasp site, relative to the base body."""
    world = World(2)
    data = world.make_data()
    for h in world.robots:
        data.qpos[list(h.arm_qpos_adr)] = q
    mujoco.mj_kinematics(world.model, data)
    for i, h in enumerate(world.robots):
        rot, pos = grasp_pose(world.robot_model(i), np.asarray(q, dtype=float))
        rot_b, pos_b = data.xmat[h.base_body].reshape(3, 3), data.xpos[h.base_body]
        want_rot = rot_b.T @ data.site_xmat[h.grasp_site].reshape(3, 3)
        want_pos = rot_b.T @ (data.site_xpos[h.grasp_site] - pos_b)
        np.testing.assert_allclose(rot, want_rot, rtol=0, atol=KINEMATICS_TOL)
        np.testing.assert_allclose(pos, want_pos, rtol=0, atol=KINEMATICS_TOL)


def _readings(gyro, accel, pos=None, quat=None) -> SensorReadings:
    """Two robots' readings, both rows the same."""
    fix = pos is not None
    pos, quat = (np.zeros(3), np.zeros(4)) if not fix else (pos, quat)
    rows = (np.tile(np.asarray(x, dtype=float), (2, 1)) for x in (accel, gyro, [0, 0], pos, quat))
    return SensorReadings(
        0.0,
        *rows,
        has_imu=np.ones(2, dtype=bool),
        has_fix=np.full(2, fix),
    )


def test_navigator_dead_reckons_and_blends_as_written():
    """Two robots, one step without a fix then one at rest with a fix: the batched kernel against
    the equations of envs/navigation.py written out with scipy's rotations."""
    world = World(2)
    robots = [world.robot_model(i) for i in range(2)]
    profile = noise_profile("nominal")
    dt = 0.016
    nav = BaseNavigator(robots, dt, profile)
    quat0 = np.array([np.cos(0.2), 0.0, 0.0, np.sin(0.2)])
    nav.reset(_readings(np.zeros(3), np.zeros(3), [0.1, 0.0, 0.0], quat0))
    r_i, p_i = robots[0].imu_rot, robots[0].imu_pos
    rot = Rotation.from_quat(quat0[[1, 2, 3, 0]]).as_matrix()
    p, v = np.array([0.1, 0.0, 0.0]) + rot @ p_i, np.zeros(3)
    gyro, accel = np.array([0.01, -0.02, 0.03]), np.array([0.002, 0.001, -0.003])
    acting = np.array([True, False])
    resting = (nav.rot[1].copy(), nav.base_pos[1].copy(), nav.base_vel[1].copy())
    nav.update(_readings(gyro, accel), acting)
    w = r_i @ gyro
    rot_mid = rot @ Rotation.from_rotvec(0.5 * dt * w).as_matrix() @ r_i
    rot = rot @ Rotation.from_rotvec(dt * w).as_matrix()
    v_new = v + dt * rot_mid @ accel
    p, v = p + 0.5 * dt * (v + v_new), v_new
    np.testing.assert_allclose(nav.rot[0], rot, atol=1e-15)
    np.testing.assert_allclose(nav.base_pos[0], p - rot @ p_i, atol=1e-15)
    np.testing.assert_allclose(nav.base_vel[0], v - rot @ np.cross(w, p_i), atol=1e-15)
    for now, before in zip((nav.rot[1], nav.base_pos[1], nav.base_vel[1]), resting, strict=True):
        np.testing.assert_array_equal(now, before)  # robot 1 does not act: untouched
    # A fix: the attitude moves by the gain times log(R^T R_fix), the IMU point by the
    # position gains times the innovation.
    att_cov = nav.att_cov[0] + nav.gyro_step_var
    fix_quat = np.array([np.cos(0.21), 0.0, 0.0, np.sin(0.21)])
    fix_pos = np.array([0.1005, 0.0, 0.0])
    before = nav.rot[0].copy()
    nav.update(_readings(np.zeros(3), np.zeros(3), fix_pos, fix_quat), acting)
    gain_att = att_cov / (att_cov + nav.att_var)
    fix_rot = Rotation.from_quat(fix_quat[[1, 2, 3, 0]]).as_matrix()
    err = Rotation.from_matrix(before.T @ fix_rot).as_rotvec()
    want = before @ Rotation.from_rotvec(gain_att * err).as_matrix()
    np.testing.assert_allclose(nav.rot[0], want, atol=1e-12)


def test_a_copied_navigator_views_its_own_filters():
    """``rot``, ``base_pos`` ... are views of the record array ``filters`` that the kernel
    updates: a deep or pickled copy gets views of its own copy, and the original is untouched."""
    world = World(2)
    robots = [world.robot_model(i) for i in range(2)]
    nav = BaseNavigator(robots, 0.016, noise_profile("nominal"))
    quat0 = np.array([np.cos(0.2), 0.0, 0.0, np.sin(0.2)])
    for twin in (copy.deepcopy(nav), pickle.loads(pickle.dumps(nav))):
        twin.reset(_readings(np.zeros(3), np.zeros(3), [0.1, 0.0, 0.0], quat0))
        twin.update(_readings([0.01, 0.0, 0.0], [0.002, 0.0, 0.0]), np.ones(2, dtype=bool))
        for name in ("rot", "base_pos", "base_vel", "w_base", "cov", "att_cov"):
            view = getattr(twin, name)
            assert np.shares_memory(view, twin.filters), name
            np.testing.assert_array_equal(view, twin.filters[name])
        assert not np.allclose(twin.base_pos, 0.0)
        np.testing.assert_array_equal(nav.rot, np.tile(np.eye(3), (2, 1, 1)))
        np.testing.assert_array_equal(nav.base_pos, 0.0)


def test_action_map_is_the_clip_and_rate_limit_as_written():
    """envs.actions.scale_actions against its docstring's equations in numpy, with one robot
    not acting (its row ignored, its targets drifting back toward the deployed pose)."""
    from astrocargo.envs.actions import ARM_DEPLOYED, ARM_OFFSET_RAD, scale_actions

    rng = np.random.default_rng(5)
    actions = rng.uniform(-2.0, 2.0, (3, 8))
    acting = np.array([True, False, True])
    limits = rng.uniform(0.1, 1.0, (3, 6))
    targets = ARM_DEPLOYED + rng.uniform(-0.3, 0.3, (3, 2))
    low, high = np.full((3, 2), -1.0), np.full((3, 2), 1.0)
    clipped, n_clipped, effort, commands, new_targets = scale_actions(
        actions, acting, limits, targets, low, high, 0.01, ARM_DEPLOYED, ARM_OFFSET_RAD
    )
    want = np.where(acting[:, None], np.clip(actions, -1.0, 1.0), 0.0)
    np.testing.assert_array_equal(clipped, want)
    np.testing.assert_array_equal(n_clipped, ((want != actions) & acting[:, None]).sum(axis=1))
    np.testing.assert_allclose(effort, (want**2).sum(axis=1), rtol=1e-15)
    np.testing.assert_array_equal(commands, want[:, :6] * limits)
    wanted = ARM_DEPLOYED + ARM_OFFSET_RAD * want[:, 6:]
    step = np.clip(wanted - targets, -0.01, 0.01)
    np.testing.assert_array_equal(new_targets, np.clip(targets + step, low, high))
