"""With ideal sensors the estimator converges to the truth whatever the arms do within their
servo limits (issue 15, item 1).

The hardest motion the servos allow: both joints driven at their 0.12 rad/s rate limit, the
requested target flipping every half period (a triangle wave of the servo targets, tilt and pan in
quadrature), thrusters idle, so the only excitation is the arm's reaction. Before the fix the
estimator's filter read the IMU's and the thrust's period means as point samples at the end of
the period, dt/2 later than the encoders' samples, and the balance kept dt/2 times the rate of
change of the arm's momentum rate: 8-20 % mass error and most updates gated. That is fixed (the
means enter the filter with a zero-order hold): no update is gated and the mass is within 1 %.

What remained after that was the balance's nonlinearity in the pre-filtered signals (rotations
by the joint angles, products of rates): the 1 Hz pre-filter distorted the harmonics of the
servo-driven motion before the products (mass 0.78 %, CoM 0.52 mm, principal moments 1.5 / 6.5 /
0.2 %). The estimator forms the balance in momentum form, d/dt P + Q with every product taken
before the linear filters (``estimator.momentum``): CoM 0.23 mm and principal moments 0.21 / 0.20
/ 0.18 %, but the mass stayed at 0.18 %, its residual at the servos' turnarounds and scaling with
dt^2.

That last residual was not the filters' (their chains are consistent: a point sample with a
first-order hold and a period mean with a zero-order hold of the new sample both pass a slow
signal with the gain sinc^2(w dt / 2)) but the servos' ripple within the period. A servo target is
held over the period, so the servo's torque K_p (T_k - q(t)) steps by K_p (T_k - T_k-1) at each
sample instant and falls back linearly over the period: a sawtooth whose response, the rates'
periodic ripple, is -(dt / 12) H^-1 [0; K_p (T_k - T_k-1)] at the sample instants (H the free
robot's and cargo's mass matrix) and averages to zero over each period. The encoders' point
samples of q do not see it (the joint angles' ripple vanishes at the sample instants), the
accelerometer's period mean does: it is the change of the IMU point's velocity between two sample
instants, so where the target rate changes (the turnarounds) it holds the change of the ripple,
d/dt of a step that no smooth model of the encoders' motion contains: about 0.15 % of the arm's
momentum swing at 62.5 Hz, the size of the mass error. The estimator now reads the
accelerometer's mean less that change (``momentum.servo_ripple_velocities``, at the current
estimate of the cargo; the servo
targets' rate is its own command, as the thrust is): mass 0.01 %, CoM 0.012 mm, principal moments
0.04 / 0.20 / 0.01 %, inside the issue's bound with margin. The ripple model is checked here
against the simulation: the mass matrix against MuJoCo's, the IMU point's velocity ripple against
its departure from the derivative of its sampled positions.

The momentum form itself is checked against two independent references: its d/dt P + Q against
the Newton-Euler balance (``rne``, itself checked against MuJoCo) on an analytic motion, and its P
against the momentum MuJoCo computes for the whole tree.
"""

import mujoco
import numpy as np
import pytest

from astrocargo.envs.transport import ARM_SPEED_RADPS, CargoTransport
from astrocargo.envs.world import World
from astrocargo.estimator import momentum as mo
from astrocargo.estimator import rne
from astrocargo.estimator.geometry import quat_to_mat
from astrocargo.estimator.inertia import transform_params
from astrocargo.estimator.preprocess import StateVariableFilter

PERIOD_S = 6.0  # the worst case (16-21 % mass error before the fix)
DURATION_S = 90.0
# The bound (must-show of issue 15 item 1).
MASS_TOL = 1e-3  # relative
COM_TOL_M = 5e-4
PRINCIPAL_TOL = 1e-2  # relative, each principal moment
# What the timing fix alone reaches (main: 40 % mass error, most updates gated).
FIXED_MASS_TOL = 1e-2
FIXED_COM_TOL_M = 1e-3


def _arm_oscillation(t_s: float, n_robots: int) -> np.ndarray:
    """Thrust idle; each arm's requested targets flip every half period (tilt and pan a quarter
    period apart, robots in opposition): the servo targets move at the rate limit throughout."""
    actions = np.zeros((n_robots, 8))
    for i in range(n_robots):
        phase = 2 * np.pi * t_s / PERIOD_S + i * np.pi
        actions[i, 6] = np.sign(np.sin(phase))
        actions[i, 7] = np.sign(np.cos(phase))
    return actions


@pytest.fixture(scope="module")
def arm_run():
    sim = CargoTransport(n_robots=1, trajectory="hover", noise="ideal", observe_estimates=False)
    sim.reset(np.random.default_rng(0))
    targets = [sim.arm_targets.copy()]
    for k in range(1, int(round(DURATION_S / sim.dt_s)) + 1):
        result = sim.step(_arm_oscillation(k * sim.dt_s, sim.n_robots))
        assert not result.terminated, result.termination_reason
        targets.append(sim.arm_targets.copy())
    return sim, np.array(targets), result.infos[0]


def test_arm_moves_at_the_servo_rate_limit(arm_run):
    sim, targets, _ = arm_run
    speed = np.abs(np.diff(targets, axis=0)) / sim.dt_s
    # The targets move at the limit nearly all the time (a triangle wave), never faster.
    assert speed.max() <= ARM_SPEED_RADPS * (1 + 1e-9)
    assert np.mean(speed > 0.99 * ARM_SPEED_RADPS) > 0.95


def test_ideal_sensors_no_timing_bias_under_fastest_arm_motion(arm_run):
    sim, _, info = arm_run
    counters = info["estimator"]
    assert counters["gated"] == 0, counters
    assert counters["updates"] > 0.9 * (DURATION_S - 5.0) * sim.control_hz / 10, counters
    assert info["mass_rel_err"] <= FIXED_MASS_TOL, info["mass_rel_err"]
    assert info["com_err_m"] <= FIXED_COM_TOL_M, info["com_err_m"]


def test_ideal_sensors_converge_under_fastest_arm_motion(arm_run):
    """The issue's bound on the mass, the centre of mass and the principal moments (the
    acceleration form left 0.78 %, 0.52 mm and 6.5 %; the momentum form without the servo
    ripple's model 0.18 % on the mass)."""
    _, _, info = arm_run
    assert info["mass_rel_err"] <= MASS_TOL, info["mass_rel_err"]
    assert info["com_err_m"] <= COM_TOL_M, info["com_err_m"]
    assert max(info["principal_rel_err"]) <= PRINCIPAL_TOL, info["principal_rel_err"]


@pytest.mark.parametrize("held", [True, False])
def test_period_means_are_held_not_points(held):
    """A signal's period means and the point samples of its second integral must give the same
    filtered signal: q(t) = sin(w t) sampled at t_k, and qdd's mean over each period
    (qd(t_k) - qd(t_k-1)) / dt, as the IMU reports it. Held (zero-order hold of the new sample
    over the period it describes) they agree to O((w dt)^2); as point samples the mean lags by
    dt/2, an error of w dt / 2 relative, which the check must see."""
    dt, w = 0.016, 2 * np.pi * 0.5
    filt = StateVariableFilter(2, dt, 1.0, held=[1] if held else None)
    t = np.arange(2000) * dt
    q, qd = np.sin(w * t), w * np.cos(w * t)
    qdd_mean = np.concatenate(([0.0], np.diff(qd) / dt))
    qdd_mean[0] = qdd_mean[1]
    out = []
    for u in zip(q, qdd_mean, strict=True):
        y, _, ydd = filt.step(np.array(u))
        out.append((ydd[0], y[1]))
    out = np.array(out)[500:]
    rel = np.max(np.abs(out[:, 0] - out[:, 1])) / np.max(np.abs(out[:, 0]))
    if held:
        assert rel < 0.2 * (w * dt) ** 2
    else:
        assert rel > 0.3 * w * dt


# ------------------------------------------------------------------ the momentum form itself
def _robot():
    return World(1).robot_model(0)


def _smooth_motion(robot, t_s: float, seed: int = 1):
    """An analytic motion (sums of sines) and its derivatives: w_B, its rate, the IMU point's
    acceleration, q, qd, qdd."""
    rng = np.random.default_rng(seed)
    nj = robot.n_joints
    amp = rng.normal(size=(4, 6 + nj))
    freq = rng.uniform(0.5, 2.0, size=(4, 6 + nj))

    def sig(d: int) -> np.ndarray:
        return np.sum(amp * freq**d * np.sin(freq * t_s + d * np.pi / 2), axis=0)

    s0, s1, s2 = sig(0), sig(1), sig(2)
    return 0.3 * s0[:3], 0.3 * s1[:3], 0.1 * s0[3:6], 0.5 * s0[6:], 0.5 * s1[6:], 0.5 * s2[6:]


def test_momentum_form_derivative_is_the_newton_euler_balance():
    """d/dt P + Q (central difference of P) equals ``rne``'s balance of the same motion: the
    links' momentum rate, the cargo's regressor and the thrust, all in G."""
    robot = _robot()
    thrust = np.random.default_rng(2).normal(size=6)
    t_s, h_s = 0.7, 1e-5

    def sample(t):
        w, _, a_imu, q, qd, _ = _smooth_motion(robot, t)
        return mo.momentum_sample(robot, w, a_imu, q, qd, thrust)[0]

    now, rate = sample(t_s), (sample(t_s + h_s) - sample(t_s - h_s)) / (2 * h_s)
    form = mo.balance_from_filtered(now, rate)
    w, wd, a_imu, q, qd, qdd = _smooth_motion(robot, t_s)
    acc_base = rne.point_acceleration(a_imu, w, wd, -np.asarray(robot.imu_pos, dtype=float))
    ref, _, _ = rne.balance_in_grasp_frame(robot, w, wd, acc_base, q, qd, qdd, thrust)
    np.testing.assert_allclose(form.thrust, ref.thrust, rtol=0, atol=1e-12)
    np.testing.assert_allclose(form.links, ref.links, rtol=0, atol=1e-8 * np.abs(ref.links).max())
    scale = np.abs(ref.regressor).max()
    np.testing.assert_allclose(form.regressor, ref.regressor, rtol=0, atol=1e-8 * scale)
    # A sign or frame error would show at O(1): the check can fail.
    assert np.abs(ref.links).max() > 0.1 and scale > 0.1


def _object_velocity(model, data, body: int, local: bool) -> np.ndarray:
    vel = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, vel, int(local))
    return vel  # [angular; linear] at the body origin


def _one_robot_world() -> World:
    """One robot holding a 4.2 kg cargo with an off-centre CoM and a full inertia tensor."""
    world = World(1)
    world.set_cargo(
        4.2,
        (0.03, -0.02, 0.05),
        np.array([[0.08, 0.01, -0.005], [0.01, 0.11, 0.004], [-0.005, 0.004, 0.12]]),
    )
    return world


@pytest.mark.parametrize("seed", [0, 1])
def test_momentum_form_p_is_mujocos_momentum(seed):
    """P_links + P_Y pi, the momentum of the robot and the cargo relative to the frame that
    translates with the IMU point (G axes, angular about G's origin), is MuJoCo's momentum of the
    whole tree: p = M v_com - M v_I and L_G = L_com + M (x_com - x_G) x (v_com - v_I)."""
    world = _one_robot_world()
    model, data = world.model, world.make_data()
    h = world.robots[0]
    robot = world.robot_model(0)
    rng = np.random.default_rng(seed)
    data.qvel[:] = rng.normal(size=model.nv) * 0.3
    data.qpos[list(h.arm_qpos_adr)] = rng.uniform(-0.5, 0.5, size=robot.n_joints)
    mujoco.mj_forward(model, data)
    mujoco.mj_subtreeVel(model, data)
    site = h.cargo_grasp_site
    rot_site = quat_to_mat(model.site_quat[site])
    cargo = transform_params(world.cargo_params(), rot_site.T, -rot_site.T @ model.site_pos[site])
    q, qd = data.qpos[list(h.arm_qpos_adr)], data.qvel[list(h.arm_dof_adr)]
    w_base = _object_velocity(model, data, h.base_body, local=True)[:3]
    sample, rot_bg, pos_bg = mo.momentum_sample(robot, w_base, np.zeros(3), q, qd, np.zeros(6))
    p_g = sample[mo.LINKS_P] + mo.cargo_regressor_parts(sample)[0] @ cargo
    rot_wb, pos_wb = data.xmat[h.base_body].reshape(3, 3), data.xpos[h.base_body]
    rot_wg, pos_wg = rot_wb @ rot_bg, pos_wb + rot_wb @ pos_bg
    world_vel = _object_velocity(model, data, h.base_body, local=False)
    imu_lever = rot_wb @ robot.imu_pos
    v_imu = world_vel[3:] + np.cross(world_vel[:3], imu_lever)
    root = model.body_rootid[h.base_body]
    total = model.body_subtreemass[root]
    v_com, x_com = data.subtree_linvel[root], data.subtree_com[root]
    expected_p = total * (v_com - v_imu)
    expected_l = data.subtree_angmom[root] + total * np.cross(x_com - pos_wg, v_com - v_imu)
    np.testing.assert_allclose(rot_wg @ p_g[:3], expected_p, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rot_wg @ p_g[3:], expected_l, rtol=0, atol=1e-9)
    assert np.linalg.norm(expected_p) > 0.1 and np.linalg.norm(expected_l) > 0.01


def test_rate_noise_bias_is_removed_in_expectation():
    """Q is quadratic in the joint rates: the mean of the sample over a rate noise of covariance
    var I (the 2 n points qd +- (n var)^(1/2) e_j have exactly that mean and covariance) is the
    noise-free sample once ``qd_var`` is given, and is not without it."""
    robot = _robot()
    w, _, a_imu, q, qd, _ = _smooth_motion(robot, 0.3)
    thrust = np.zeros(6)
    nj, var = robot.n_joints, 0.01
    clean = mo.momentum_sample(robot, w, a_imu, q, qd, thrust)[0]
    points = [qd + sign * np.sqrt(nj * var) * e for e in np.eye(nj) for sign in (1, -1)]
    corrected = np.mean(
        [mo.momentum_sample(robot, w, a_imu, q, x, thrust, np.full(nj, var))[0] for x in points],
        axis=0,
    )
    raw = np.mean([mo.momentum_sample(robot, w, a_imu, q, x, thrust)[0] for x in points], axis=0)
    np.testing.assert_allclose(corrected, clean, rtol=0, atol=1e-12)
    assert np.abs(raw - clean).max() > 1e-4


def test_cargo_channels_map_to_the_body_regressor():
    """The filters run on the cargo's 6 + 9 arguments: P_Y = Y(nu, 0, w) and Q_Y = Y(c, w, 0)
    are exactly the fixed maps of them (a dropped cross term of w would show at O(1))."""
    rng = np.random.default_rng(4)
    for _ in range(3):
        nu, w, c = rng.normal(size=(3, 3))
        x = np.zeros(mo.SIZE)
        x[mo.CARGO_P] = np.concatenate((nu, w))
        x[mo.CARGO_Q] = np.concatenate((c, [w[i] * w[j] for i, j in mo._PRODUCTS]))
        p_y, q_y = mo.cargo_regressor_parts(x)
        np.testing.assert_allclose(p_y, rne.body_regressor(nu, np.zeros(3), w), atol=1e-14)
        np.testing.assert_allclose(q_y, rne.body_regressor(c, w, np.zeros(3)), atol=1e-14)


def test_momentum_sample_rejects_bad_shapes():
    robot = _robot()
    nj = robot.n_joints
    with pytest.raises(ValueError, match="qd must have shape"):
        mo.momentum_sample(robot, np.zeros(3), np.zeros(3), np.zeros(nj), np.zeros(nj + 1),
                           np.zeros(6))  # fmt: skip


# ------------------------------------------------------------------ the servos' ripple
def _cargo_in_grasp_frame(world: World, i: int = 0) -> np.ndarray:
    """The true cargo's standard parameters in robot i's grasp frame G, about G's origin."""
    site = world.robots[i].cargo_grasp_site
    rot_site = quat_to_mat(world.model.site_quat[site])
    return transform_params(
        world.cargo_params(), rot_site.T, -rot_site.T @ world.model.site_pos[site]
    )


def test_generalised_inertia_is_mujocos_mass_matrix():
    """``generalised_inertia`` in u = [v_B; w_B; qd] (B axes) is MuJoCo's mass matrix of the
    same tree (rooted at the cargo there) after the change of coordinates qvel -> u."""
    world = _one_robot_world()
    model, data = world.model, world.make_data()
    h, robot = world.robots[0], world.robot_model(0)
    data.qpos[list(h.arm_qpos_adr)] = np.random.default_rng(0).uniform(-0.5, 0.5, size=2)
    mujoco.mj_forward(model, data)
    q = data.qpos[list(h.arm_qpos_adr)].copy()

    def u_of(qvel: np.ndarray) -> np.ndarray:
        data.qvel[:] = qvel
        mujoco.mj_forward(model, data)
        vel = _object_velocity(model, data, h.base_body, local=True)
        return np.concatenate((vel[3:], vel[:3], data.qvel[list(h.arm_dof_adr)]))

    to_u = np.array([u_of(e) for e in np.eye(model.nv)]).T
    from_u = np.linalg.inv(to_u)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    expected = from_u.T @ full @ from_u
    got = mo.generalised_inertia(robot.arrays, q, _cargo_in_grasp_frame(world))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_servo_ripple_is_the_imu_velocitys_departure_from_its_sampled_positions():
    """Both servos driven at the rate limit: at the sample instants the IMU point's velocity
    departs from the derivative of its sampled positions (which hold no ripple) by
    ``servo_ripple``, the sawtooth's response -(dt / 12) H^-1 [0; K_p dT] (module docstring)."""
    sim = CargoTransport(n_robots=1, trajectory="hover", noise="ideal", observe_estimates=False)
    sim.reset(np.random.default_rng(0))
    world, model, data, dt = sim.world, sim.model, sim.data, sim.dt_s
    h, robot = world.robots[0], world.robot_model(0)
    cargo = _cargo_in_grasp_frame(world)
    action = np.zeros((1, 8))
    action[0, 6:] = (1.0, -1.0)
    pos, vel, predicted = [], [], []
    for _ in range(60):
        sim.step(action)
        q = data.qpos[list(h.arm_qpos_adr)]
        v = np.zeros(6)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, h.imu_site, v, 0)
        pos.append(data.site_xpos[h.imu_site].copy())
        vel.append(v[3:])
        rot_wb = data.xmat[h.base_body].reshape(3, 3)
        predicted.append(rot_wb @ mo.servo_ripple(robot, q, cargo, sim.arm_rates[0], dt))
    pos, vel, predicted = np.array(pos), np.array(vel)[2:-2], np.array(predicted)[2:-2]
    smooth = (-pos[4:] + 8 * pos[3:-1] - 8 * pos[1:-3] + pos[:-4]) / (12 * dt)
    measured = (vel - smooth)[10:]
    scale = np.abs(predicted[10:]).max()
    np.testing.assert_allclose(measured, predicted[10:], rtol=0, atol=0.03 * scale)
    assert scale > 1e-6  # m/s: a sign or factor error would show
