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
from astrocargo.estimator import rne
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
    vec_to_inertia,
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


def test_filter_noise_gains_are_the_impulse_response_energy():
    """The closed form (discrete Lyapunov equation) equals stepping a unit impulse through the
    filter until it has died out."""
    for cutoff in (0.25, 1.0):
        f = StateVariableFilter(1, DT, cutoff)
        f.step(np.zeros(1))
        energy = np.zeros(3)
        for k in range(int(20 * f.delay_s / DT)):
            energy += np.concatenate(f.step(np.array([1.0 if k == 0 else 0.0]))) ** 2
        np.testing.assert_allclose(f.noise_gains(), np.sqrt(energy), rtol=1e-12)


def test_filter_starts_in_its_steady_state():
    """(I - Ad)^-1 b_value u = (u, 0, 0): a constant input leaves the started filter at rest."""
    f = StateVariableFilter(2, DT, 1.0)
    np.testing.assert_allclose(np.linalg.solve(np.eye(3) - f.ad, f.b_value), [1, 0, 0], atol=1e-9)
    u = np.array([0.3, -2.0])
    first = np.array(f.step(u))
    for _ in range(50):
        y = np.array(f.step(u))
    np.testing.assert_allclose(y, first, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(first, [u, [0, 0], [0, 0]])


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
    # The Fisher information of the same data says which: two principal moments get less than the
    # prior's own information (the controller's small off-axis corrections give them a little:
    # with the floors at the momentum form's model error, 0.09 / 0.45 / 0.63 of the prior's
    # information on the three weakest functionals, against 2.7e5 on I_xx's).
    prior_cov = prior.params_cov()
    fisher = fisher_information(Recording.from_log(est.log))
    unseen = unrevealed_directions(fisher, prior_cov, ratio=1.0)
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


# --------------------------------------------------------------------------- sub-body model
def _rodrigues(axis, angle):
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def _reference_balance(robot, w_base, wd_base, acc_base, q, qd, qdd, thrust_base):
    """The seed paper's recursion (eq. 1-6) written plainly, link by link, for one sample:
    thrust, links and the cargo regressor in G, and G's pose in B."""
    rots, poss, ws, wds, accs = [np.eye(3)], [np.zeros(3)], [w_base], [wd_base], [acc_base]
    for k, link in enumerate(robot.links[1:], start=1):
        p = link.parent
        rot = rots[p] @ link.rot_in_parent @ _rodrigues(link.joint_axis, q[k - 1])
        r = rots[p] @ link.pos_in_parent
        z = rot @ link.joint_axis
        rots.append(rot)
        poss.append(poss[p] + r)
        ws.append(ws[p] + qd[k - 1] * z)
        wds.append(wds[p] + qdd[k - 1] * z + np.cross(ws[p], qd[k - 1] * z))
        accs.append(accs[p] + np.cross(wds[p], r) + np.cross(ws[p], np.cross(ws[p], r)))
    links = np.zeros(6)
    for k, link in enumerate(robot.links):
        c = rots[k] @ link.com
        f = link.mass * (accs[k] + np.cross(wds[k], c) + np.cross(ws[k], np.cross(ws[k], c)))
        inertia = rots[k] @ link.inertia_com @ rots[k].T
        n = inertia @ wds[k] + np.cross(ws[k], inertia @ ws[k]) + np.cross(poss[k] + c, f)
        links += np.concatenate((f, n))
    g = robot.grasp_link
    r_g = rots[g] @ robot.grasp_pos
    rot_g, pos_g = rots[g] @ robot.grasp_rot, poss[g] + r_g
    acc_g = accs[g] + np.cross(wds[g], r_g) + np.cross(ws[g], np.cross(ws[g], r_g))

    def to_grasp(wrench):
        return np.concatenate(
            (rot_g.T @ wrench[:3], rot_g.T @ (wrench[3:] - np.cross(pos_g, wrench[:3])))
        )

    # Columns of Y: the cargo's momentum rate in G for each unit parameter, from its definition
    # f = m a + wd x h + w x (w x h), n = I wd + w x I w + h x a.
    a, w, wd = rot_g.T @ acc_g, rot_g.T @ ws[g], rot_g.T @ wds[g]
    regressor = np.zeros((6, 10))
    for i in range(10):
        pi = np.eye(10)[i]
        m, h = pi[0], pi[1:4]
        inertia = vec_to_inertia(pi[4:])
        f = m * a + np.cross(wd, h) + np.cross(w, np.cross(w, h))
        n = inertia @ wd + np.cross(w, inertia @ w) + np.cross(h, a)
        regressor[:, i] = np.concatenate((f, n))
    return to_grasp(thrust_base), to_grasp(links), regressor, rot_g, pos_g


def _random_motion(rng, n_joints, batch=()):
    w, wd, acc = rng.normal(size=(3, *batch, 3))
    q, qd, qdd = rng.normal(size=(3, *batch, n_joints))
    return w, wd, acc, q, qd, qdd


def test_balance_equals_the_plain_recursion():
    """The compiled two-pass model is the seed paper's recursion (which tests/test_rne_mujoco.py
    holds against MuJoCo), written plainly in the test."""
    robot = World(1).robot_model(0)
    rng = np.random.default_rng(3)
    for _ in range(20):
        motion = _random_motion(rng, robot.n_joints)
        thrust = rne.thrust_wrench(robot, rng.normal(size=6))
        expected = _reference_balance(robot, *motion, thrust)
        balance, rot, pos = rne.balance_in_grasp_frame(robot, *motion, thrust)
        got = (balance.thrust, balance.links, balance.regressor, rot, pos)
        for e, g in zip(expected, got, strict=True):
            np.testing.assert_allclose(g, e, rtol=0, atol=1e-12)
        kin = rne.propagate(robot, *motion)
        to_g = rne.grasp_from_base(kin.grasp_rot, kin.grasp_pos)
        np.testing.assert_allclose(to_g @ rne.link_momentum_rate(robot, kin), got[1], atol=1e-12)
        np.testing.assert_allclose(
            to_g @ rne.wrench_transform(kin.grasp_rot, kin.grasp_pos), np.eye(6), atol=1e-12
        )
        np.testing.assert_allclose(to_g @ rne.cargo_regressor(kin), got[2], atol=1e-12)


def test_batched_model_equals_per_sample():
    robot = World(1).robot_model(0)
    rng = np.random.default_rng(4)
    motion = _random_motion(rng, robot.n_joints, batch=(2, 3))
    kin = rne.propagate(robot, *motion)
    links = rne.link_momentum_rate(robot, kin)
    cargo = rne.cargo_regressor(kin)
    regressor = rne.body_regressor(*motion[:3])
    assert kin.rot.shape == (2, 3, len(robot.links), 3, 3) and cargo.shape == (2, 3, 6, 10)
    for index in np.ndindex(2, 3):
        single = rne.propagate(robot, *(x[index] for x in motion))
        np.testing.assert_array_equal(kin.grasp_acc[index], single.grasp_acc)
        np.testing.assert_array_equal(links[index], rne.link_momentum_rate(robot, single))
        np.testing.assert_array_equal(cargo[index], rne.cargo_regressor(single))
        np.testing.assert_array_equal(
            regressor[index], rne.body_regressor(*(x[index] for x in motion[:3]))
        )
    rot, pos = rne.grasp_pose(robot, motion[3][0, 0])
    rots, poss = rne.link_poses(robot, motion[3][0, 0])
    np.testing.assert_allclose(rot, rots[robot.grasp_link] @ robot.grasp_rot, atol=1e-15)
    np.testing.assert_allclose(
        pos, poss[robot.grasp_link] + rots[robot.grasp_link] @ robot.grasp_pos, atol=1e-15
    )


def test_model_inputs_are_checked():
    robot = World(1).robot_model(0)
    zeros = [np.zeros(3)] * 3 + [np.zeros(robot.n_joints)] * 3
    with pytest.raises(ValueError, match="q must have shape"):
        rne.balance_in_grasp_frame(robot, *zeros[:3], np.zeros(3), *zeros[4:], np.zeros(6))
    with pytest.raises(ValueError, match="thrust_base must have shape"):
        rne.balance_in_grasp_frame(robot, *zeros, np.zeros(3))
    with pytest.raises(ValueError, match="wd_base must have shape"):
        rne.propagate(robot, np.zeros((4, 3)), np.zeros(3), *zeros[2:])
    with pytest.raises(ValueError, match="balance vector"):
        rne.Balance.from_vector(np.zeros(71))


def test_balance_vector_round_trip_and_robot_arrays():
    rng = np.random.default_rng(6)
    balance = rne.Balance(rng.normal(size=6), rng.normal(size=6), rng.normal(size=(6, 10)))
    again = rne.Balance.from_vector(balance.to_vector())
    for name in ("thrust", "links", "regressor"):
        np.testing.assert_array_equal(getattr(again, name), getattr(balance, name))
    robot = World(1).robot_model(0)
    assert robot.arrays is robot.arrays  # packed once
    np.testing.assert_array_equal(robot.arrays.mass, [link.mass for link in robot.links])
    np.testing.assert_array_equal(robot.arrays.joint_axis[1], robot.links[1].joint_axis)


def test_peer_slots_follow_every_new_message_and_are_read_only():
    """The env's peer slots are kept between messages: each newly delivered message must show in
    them at once (wrench, arrival), the ages must grow with the step, and what is returned must
    not be writable (it is shared with later calls)."""
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(n_robots=2, noise="nominal")
    env.reset(seed=4)
    team = env.sim.estimation
    acting = np.ones(2, dtype=bool)
    seen_stamps = set()
    for k in range(1, 400):
        env.step({a: 0.1 * np.ones(8) for a in env.agents})
        wrench, age, valid, _ = team.peer_slot_values(acting, k)
        for i, j in ((0, 1), (1, 0)):
            msg = team.peer_msgs[i].get(j)
            if msg is None:
                assert valid[i, 0] == 0.0 and not wrench[i, 0].any()
                continue
            seen_stamps.add(msg.stamp)
            np.testing.assert_array_equal(wrench[i, 0], msg.wrench_world)
            assert valid[i, 0] == 1.0
            assert age[i, 0] == pytest.approx((k - msg.stamp) * env.sim.dt_s)
    assert len(seen_stamps) > 5  # several messages replaced one another in the slots
    with pytest.raises(ValueError):
        wrench[0, 0, 0] = 1.0


def test_peer_terms_sum_each_peer_in_order():
    """``_peer_terms``: the peers' wrenches T_j w_j, the carried actuation covariances
    T_j C_j T_j^T and the added noise (channel noise T_j N T_j^T; the averaged relative pose's
    for a layout not given) summed over the peers in order, exactly as peer by peer."""
    from types import SimpleNamespace

    world = World(4)
    rng = np.random.default_rng(7)
    layout = {j: world.relative_grasp(0, j) for j in (1, 3)}  # peer 2's layout is estimated
    est = CargoEstimator(
        world.robot_model(0), 0, [1, 2, 3], DT, relative_grasps=layout,
        peer_noise_std=(0.01, 0.001),
    )  # fmt: skip
    rel = est._relative[2]
    rot, pos = world.relative_grasp(0, 2)
    rel.rot_sum, rel.pos_sum, rel.count = 3.0 * np.asarray(rot), 3.0 * np.asarray(pos), 3
    act_cov = np.diag(rng.uniform(1e-6, 1e-5, 6))
    msgs = []
    for _ in est.peers:
        half = rng.normal(size=(6, 6)) * 1e-3
        msgs.append(
            SimpleNamespace(wrench_grasp=rng.normal(size=6), wrench_cov_grasp=half @ half.T)
        )
    wrench_sum, cov, noise = est._peer_terms(act_cov, msgs)
    want_wrench, want_cov, want_noise = np.zeros(6), act_cov.copy(), np.zeros((6, 6))
    for p, m in zip(est.peers, msgs, strict=True):
        t = est._relative[p].transform()
        want_wrench += t @ m.wrench_grasp
        want_cov += t @ m.wrench_cov_grasp @ t.T
        want_noise += t @ est.noise.peer_noise_cov @ t.T
        if p == 2:
            want_noise += est.noise.relative_pose_cov(t @ m.wrench_grasp, 3)
    np.testing.assert_array_equal(wrench_sum, want_wrench)
    np.testing.assert_array_equal(cov, want_cov)
    np.testing.assert_array_equal(noise, want_noise)
    assert np.abs(noise).max() > 0.0
    lone = CargoEstimator(world.robot_model(0), 0, [], DT)
    got = lone._peer_terms(act_cov, [])
    np.testing.assert_array_equal(got[0], np.zeros(6))
    np.testing.assert_array_equal(got[1], act_cov)
    np.testing.assert_array_equal(got[2], np.zeros((6, 6)))
