"""The env's period stepping (envs.physics) against plain mj_step + the forward stages, and the
fused sensor read (SensorSuite.read_into) against read_arrays."""

import copy

import mujoco
import numpy as np

from astrocargo.envs import astrobee_cargo_v0
from astrocargo.envs.physics import PeriodStepper
from astrocargo.envs.sensors import SensorReadings, SensorSuite, imu_state_into, noise_profile
from astrocargo.envs.world import World

FIELDS = ("qpos", "qvel", "qacc_warmstart", "xpos", "xmat", "cvel", "subtree_com", "sensordata")


def _reference_period(model, data):
    """What the stepper must equal: mj_step, then the position and velocity stages."""
    mujoco.mj_step(model, data)
    mujoco.mj_fwdPosition(model, data)
    mujoco.mj_sensorPos(model, data)
    mujoco.mj_fwdVelocity(model, data)


def test_period_stepper_equals_mj_step_bit_for_bit():
    """Three robots under random controls for 400 periods, with the state written from outside
    twice (the stepper must notice and step in full): every field the env reads is identical."""
    world = World(3)
    model = world.model
    ours, theirs = world.make_data(), world.make_data()
    stepper = PeriodStepper(model, ours, 1)
    assert stepper.skip_allowed  # the MJCF integrates with RK4
    stepper.forward_done()
    rng = np.random.default_rng(0)
    skipped = 0
    for k in range(400):
        if k in (150, 300):  # a push from outside, without mj_forward
            kick = rng.normal(0.0, 0.01, model.nv)
            ours.qvel[:] += kick
            theirs.qvel[:] += kick
        ctrl = rng.uniform(-0.3, 0.3, model.nu)
        ours.ctrl[:], theirs.ctrl[:] = ctrl, ctrl
        unchanged = stepper.unchanged()
        skipped += unchanged
        assert stepper.advance(unchanged)
        _reference_period(model, theirs)
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), name)
        assert ours.time == theirs.time
    assert skipped == 398  # all but the two pushed periods skipped the first kinematics


def test_period_stepper_reports_a_non_finite_state(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the cwd
    world = World(1)
    data = world.make_data()
    stepper = PeriodStepper(world.model, data, 1)
    stepper.forward_done()
    data.qvel[:] = np.nan
    assert not stepper.unchanged()
    assert not stepper.advance(False)


def test_a_state_beyond_mujocos_bound_is_stepped_in_full(tmp_path, monkeypatch):
    """A finite entry beyond mjMAXVAL, unchanged since the last period, is one mj_checkVel acts
    on: the stepper does not take the state as unchanged (it leaves that check out then), and
    its full step resets the state and reports it unstable, as mj_step does."""
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the cwd
    world = World(1)
    ours, theirs = world.make_data(), world.make_data()
    stepper = PeriodStepper(world.model, ours, 1)
    for data in (ours, theirs):
        data.qvel[0] = 2.0 * mujoco.mjMAXVAL
    stepper.forward_done()
    assert not stepper.unchanged()
    assert not stepper.advance(stepper.unchanged())
    _reference_period(world.model, theirs)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), name)


def test_a_copied_env_steps_like_the_original():
    """A deep copy steps its first period in full, then both continue bit for bit."""
    env = astrobee_cargo_v0.parallel_env(n_robots=2, estimators=False, observe_estimates=False)
    env.reset(seed=3)
    actions = {a: np.full(8, 0.05) for a in env.agents}
    for _ in range(5):
        env.step(actions)
    twin = copy.deepcopy(env)
    for _ in range(5):
        obs, rewards, *_ = env.step(actions)
        obs_twin, rewards_twin, *_ = twin.step(actions)
        for agent in env.agents:
            np.testing.assert_array_equal(obs[agent], obs_twin[agent])
            assert rewards[agent] == rewards_twin[agent]


def test_read_into_equals_read_arrays():
    """The fused read gives read_arrays' numbers (same draws), rows by robot index, and leaves
    the IMU states of the period's end as the next start."""
    world = World(2)
    model, data = world.model, world.make_data()
    profile = noise_profile("nominal")
    suites = [SensorSuite(world, profile, np.random.default_rng(4)) for _ in range(2)]
    data.ctrl[:] = 0.2
    mujoco.mj_step(model, data, nstep=20)
    mujoco.mj_forward(model, data)
    v0, r0 = np.zeros((2, 3)), np.zeros((2, 3, 3))
    views = (data.cvel, data.site_xpos, data.site_xmat, data.subtree_com, data.sensordata)
    imu_state_into(v0, r0, *views[:4], suites[1].imu_index)
    for step in (20, 21):  # with and without a localization fix
        suites[0].begin_period(data)
        np.testing.assert_array_equal(v0, suites[0]._start[0])  # read_into's end is this start
        np.testing.assert_array_equal(r0, suites[0]._start[1])
        start = (v0, r0, float(data.time))
        mujoco.mj_step(model, data, nstep=1)
        mujoco.mj_forward(model, data)
        expected = suites[0].read_arrays(data, step)
        out = SensorReadings.empty(2)
        suites[1].read_into(views, float(data.time), step % 20 == 0, start, np.arange(2), out)
        for name in ("accel_imu", "gyro_imu", "joint_pos_rad", "base_pos_world",
                     "base_quat_world", "has_imu", "has_fix"):  # fmt: skip
            np.testing.assert_array_equal(getattr(out, name), getattr(expected, name), name)
