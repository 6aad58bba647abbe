"""The estimator pipeline: pre-filter, per-robot cargo estimator and its baselines.

World-based tests drive the robots with the cooperative controller on the true state (the env's
job, done here directly so the estimator is tested on its own) and feed each estimator only what
its robot senses.
"""

import mujoco
import numpy as np
import pytest
from true_state import true_states

from astrocargo.agents.controllers import CooperativeController
from astrocargo.agents.trajectories import Trajectory
from astrocargo.envs.sensors import SensorSuite, estimator_noise_kwargs, noise_profile
from astrocargo.envs.world import World
from astrocargo.estimator.baselines import (
    Recording,
    batch_wls,
    crlb,
    fisher_information,
    unrevealed_directions,
)
from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.inertia import (
    com_error_m,
    mass_rel_error,
    physical_violation,
)
from astrocargo.estimator.preprocess import StateVariableFilter

DT = 0.016
CARGO = (
    5.0,
    (0.02, -0.03, 0.04),
    np.array([[0.07, 0.005, 0.0], [0.005, 0.10, -0.004], [0.0, -0.004, 0.11]]),
)


# --------------------------------------------------------------------------- pre-filter
def test_filter_ramp_has_exact_derivatives():
    f = StateVariableFilter(2, DT, 1.0)
    for k in range(2000):
        y, yd, ydd = f.step(np.array([0.02 * k * DT, -0.3 * k * DT]))
    np.testing.assert_allclose(yd, [0.02, -0.3], rtol=1e-9)
    np.testing.assert_allclose(ydd, 0.0, atol=1e-12)
    np.testing.assert_allclose(y, np.array([0.02, -0.3]) * (1999 * DT - f.delay_s), rtol=1e-6)


def test_filter_derivatives_of_a_sine_are_the_filtered_derivatives():
    """y' and y'' equal the filter's response to the true derivatives (d/dt H u = H du/dt)."""
    w = 0.7
    f0, f1, f2 = (StateVariableFilter(1, DT, 1.0) for _ in range(3))
    for k in range(3000):
        t = k * DT
        y, yd, ydd = f0.step(np.array([np.sin(w * t)]))
        d1 = f1.step(np.array([w * np.cos(w * t)]))[0]
        d2 = f2.step(np.array([-w * w * np.sin(w * t)]))[0]
    np.testing.assert_allclose(yd, d1, atol=1e-4 * w)
    np.testing.assert_allclose(ydd, d2, atol=1e-4 * w * w)


def test_filter_step_is_the_first_order_hold_recurrence():
    """The filter's one-product step equals Ad y + b_value u_k + b_slope (u_k+1 - u_k)."""
    rng = np.random.default_rng(3)
    f = StateVariableFilter(4, DT, 1.0)
    inputs = rng.normal(size=(50, 4))
    state = np.zeros((3, 4))
    state[0] = inputs[0]
    f.step(inputs[0])
    for u_prev, u in zip(inputs[:-1], inputs[1:], strict=True):
        state = f.ad @ state + f.b_value[:, None] * u_prev + f.b_slope[:, None] * (u - u_prev)
        y, yd, ydd = f.step(u)
        np.testing.assert_allclose(np.array([y, yd, ydd]), state, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(f.u_prev, u)


@pytest.mark.parametrize("cutoff", [0.0, -1.0, 40.0, np.nan])
def test_filter_rejects_bad_cutoff(cutoff):
    with pytest.raises(ValueError, match="cutoff"):
        StateVariableFilter(1, DT, cutoff)


# --------------------------------------------------------------------------- world runs
def simulate(n_robots, noise, seconds, trajectory, seed=0, pan=True, estimator_kwargs=None):
    """Controller on the true state; each estimator fed its robot's own sensors and command."""
    world = World(n_robots)
    model, data = world.model, world.make_data()
    world.set_cargo(*CARGO)
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(seed)
    sensors = SensorSuite(world, noise_profile(noise), rng)
    robots = [world.robot_model(i) for i in range(n_robots)]
    kwargs = {**estimator_noise_kwargs(noise_profile(noise)), **(estimator_kwargs or {})}
    estimators = []
    for i in range(n_robots):
        peers = [j for j in range(n_robots) if j != i]
        layout = {j: world.relative_grasp(i, j) for j in peers}
        estimators.append(CargoEstimator(robots[i], i, peers, DT, relative_grasps=layout, **kwargs))
    controller = CooperativeController(robots)
    ref_fn = Trajectory(trajectory, pan_ramp=pan)
    truth = world.cargo_params()
    nsub = round(DT / model.opt.timestep)
    for k in range(int(seconds / DT)):
        ref = ref_fn(k * DT)
        cargo, states = true_states(world, data)
        commands = controller.commands(ref, cargo, states, truth)
        for h, cmd in zip(world.robots, commands, strict=True):
            data.ctrl[list(h.thrust_actuators)] = sensors.actuate(cmd)
            data.ctrl[list(h.arm_actuators)] = [-np.pi / 2, ref.pan]
        sensors.begin_period(data)
        mujoco.mj_step(model, data, nstep=nsub)
        mujoco.mj_forward(model, data)
        assert data.ncon == 0
        messages = []
        for est, p, cmd in zip(estimators, sensors.read(data, k), commands, strict=True):
            msg = est.step(
                k,
                p.accel_imu,
                p.gyro_imu,
                p.joint_pos_rad,
                cmd,
                p.base_pos_world,
                p.base_quat_world,
            )
            if msg is not None:
                messages.append(msg)
        for est in estimators:
            for msg in messages:
                est.receive(msg)
            est.process()
    return world, estimators


@pytest.fixture(scope="module")
def ideal_two_robots():
    return simulate(2, "ideal", 40.0, "figure8_tumble", estimator_kwargs={"record": True})


def test_ideal_two_robots_converge_and_agree(ideal_two_robots):
    world, estimators = ideal_two_robots
    for i, est in enumerate(estimators):
        truth = world.cargo_params_in_grasp_frame(i)
        est_pi = est.params_mean()
        assert est.counters["updates"] > 150
        assert est.counters["skipped_missing"] == 0
        assert mass_rel_error(est_pi, truth) < 2e-3
        assert com_error_m(est_pi, truth) < 2e-3
        # Consistent: the error within 3 standard deviations of the filter's own covariance.
        z = (est_pi - truth) / est.params_std()
        assert np.all(np.abs(z) < 3.0), z


def test_batch_wls_and_crlb_on_the_same_data(ideal_two_robots):
    world, estimators = ideal_two_robots
    est = estimators[0]
    rec = Recording.from_log(est.log)
    truth = world.cargo_params_in_grasp_frame(0)
    pi_wls, cov = batch_wls(rec)
    assert mass_rel_error(pi_wls, truth) < 2e-3
    bound = crlb(rec, truth)
    assert bound["unobservable"] == []
    # The filter cannot beat the Bayesian bound by much in any parameter.
    prior = CargoEstimator(world.robot_model(0), 0, [1], DT)
    bayes = crlb(rec, truth, prior_cov=prior.params_cov())
    assert np.all(est.params_std() > 0.3 * bayes["std_params"])
    np.testing.assert_allclose(fisher_information(rec), fisher_information(rec).T, rtol=1e-12)


def _inertia_com_std(est):
    """Reported spread of the inertia about the centre of mass (grasp-frame axes):
    [xx, yy, zz, xy, xz, yz]."""
    return est.physical_estimate()[1][4:]


def test_yaw_only_leaves_two_moments_unseen():
    """Rotation about one axis (the grasp frame's x axis is the module's yaw axis): the inertia
    about the centre of mass is then seen only through I_xx, I_xy and I_xz; I_yy, I_zz and I_yz
    get no information, and the filter's uncertainty about them stays near the prior's."""
    world, estimators = simulate(
        1, "ideal", 30.0, "figure8_yaw", pan=False, estimator_kwargs={"record": True}
    )
    est = estimators[0]
    prior = CargoEstimator(world.robot_model(0), 0, [], DT)
    assert est.params_std()[0] < 0.05 * prior.params_std()[0]  # mass learned
    ratio = _inertia_com_std(est) / _inertia_com_std(prior)
    # I_yy and I_zz are not revealed: their spread stays near the prior's (only their sum with
    # I_xx's partners is pinned). I_yz gets no information either, but physical consistency bounds
    # it by the (learned) second moments, |S_yz| <= sqrt(S_yy S_zz), so its spread legitimately
    # shrinks: it is not asserted here.
    assert np.all(ratio[[1, 2]] > 0.3), ratio
    assert ratio[0] < 0.1, ratio  # I_xx: revealed
    # The Fisher information of the same data says which: two principal moments get (almost) none
    # (the third functional, I_yz, gets a little from the controller's small off-axis corrections).
    prior_cov = prior.params_cov()
    unseen = unrevealed_directions(fisher_information(Recording.from_log(est.log)), prior_cov)
    assert len(unseen) >= 2


# --------------------------------------------------------------------------- bad input
def _estimator():
    world = World(1)
    return CargoEstimator(world.robot_model(0), 0, [], DT)


def test_nan_reading_is_skipped_and_counted():
    world, _ = simulate(1, "ideal", 0.1, "hover")
    est = CargoEstimator(world.robot_model(0), 0, [], DT, warmup_s=0.5)
    rng = np.random.default_rng(0)
    for k in range(400):
        accel = 1e-3 * rng.standard_normal(3)
        if k == 200:
            accel[1] = np.nan
        est.step(
            k,
            accel,
            1e-3 * rng.standard_normal(3),
            np.array([-np.pi / 2, 0.0]),
            0.01 * rng.standard_normal(6),
            np.zeros(3),
            np.array([1.0, 0, 0, 0]),
        )
        est.process()
    assert est.counters["bad_readings"] == 1
    assert est.counters["skipped_bad_reading"] > 0
    p = est.ukf.P
    np.testing.assert_array_equal(p, p.T)
    np.linalg.cholesky(p)
    assert physical_violation(est.params_mean()) is None


@pytest.mark.parametrize(
    ("accel", "gyro", "q", "thrust"),
    [
        (np.zeros(2), np.zeros(3), np.zeros(2), np.zeros(6)),
        (np.zeros(3), np.zeros(4), np.zeros(2), np.zeros(6)),
        (np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(6)),
        (np.zeros(3), np.zeros(3), np.zeros(2), np.zeros(3)),
    ],
)
def test_wrong_shapes_raise(accel, gyro, q, thrust):
    with pytest.raises(ValueError, match="shape"):
        _estimator().step(0, accel, gyro, q, thrust)


def test_missing_peer_message_is_skipped_and_counted():
    world = World(2)
    est = CargoEstimator(world.robot_model(0), 0, [1], DT, warmup_s=0.2, history_s=0.5)
    for k in range(200):
        est.step(
            k,
            np.zeros(3),
            np.zeros(3),
            np.array([-np.pi / 2, 0.0]),
            np.zeros(6),
            np.zeros(3),
            np.array([1.0, 0, 0, 0]),
        )
        est.process()
    assert est.counters["updates"] == 0
    assert est.counters["skipped_missing"] > 0


def test_fast_balance_equals_the_batched_model():
    """The single-sample fast path is the same model as propagate / link_momentum_rate /
    body_regressor (which tests/test_rne_mujoco.py holds against MuJoCo)."""
    from astrocargo.estimator import rne

    robot = World(1).robot_model(0)
    rng = np.random.default_rng(3)
    for _ in range(20):
        w, wd, acc = rng.normal(size=(3, 3))
        q, qd, qdd = rng.normal(size=(3, 2))
        thrust = rng.normal(size=6)
        kin = rne.propagate(robot, w, wd, acc, q, qd, qdd)
        to_g = rne.grasp_from_base(kin.grasp_rot, kin.grasp_pos)
        rot_t = kin.grasp_rot.T
        expected = (
            to_g @ rne.thrust_wrench(robot, thrust),
            to_g @ rne.link_momentum_rate(robot, kin),
            rne.body_regressor(rot_t @ kin.grasp_acc, rot_t @ kin.grasp_w, rot_t @ kin.grasp_wd),
            kin.grasp_rot,
            kin.grasp_pos,
        )
        got = rne.balance_in_grasp_frame(
            robot, w, wd, acc, q, qd, qdd, rne.thrust_wrench(robot, thrust)
        )
        for e, g in zip(expected, got, strict=True):
            np.testing.assert_allclose(g, e, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            to_g @ rne.wrench_transform(kin.grasp_rot, kin.grasp_pos), np.eye(6), atol=1e-12
        )


def test_float_helpers_are_the_numpy_products():
    """rne's helpers on tuples of floats (the env's and the estimator's per-step paths) compute
    numpy's products, up to rounding."""
    from astrocargo.estimator import rne

    rng = np.random.default_rng(5)
    for _ in range(50):
        a, b = rng.normal(size=(2, 3, 3))
        u, v, w, r = rng.normal(size=(4, 3))
        ra, rb = rne.as_rows(a), rne.as_rows(b)
        for got, expected in (
            (rne.m_m(ra, rb), a @ b),
            (rne.mt_m(ra, rb), a.T @ b),
            (rne.m_mt(ra, rb), a @ b.T),
            (rne.m_v(ra, tuple(u)), a @ u),
            (rne.mt_v(ra, tuple(u)), a.T @ u),
            (
                rne.point_acc(tuple(u), tuple(w), tuple(v), tuple(r)),
                u + np.cross(v, r) + np.cross(w, np.cross(w, r)),
            ),
        ):
            np.testing.assert_allclose(np.array(got), expected, rtol=1e-13, atol=1e-13)
        # Different summation orders (np.linalg.norm goes through the CPU's BLAS kernel): equal
        # within a few ulps, never bit for bit.
        np.testing.assert_array_max_ulp(rne.cross(u, v), np.cross(u, v), maxulp=4)
        np.testing.assert_array_max_ulp(rne.cross(a, b), np.cross(a, b), maxulp=4)
        np.testing.assert_array_max_ulp(rne.norm3(u), np.linalg.norm(u), maxulp=4)
