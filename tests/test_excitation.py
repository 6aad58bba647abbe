"""The excitation designer (agents/excitation_design.py) and its designs (agents/excitation.py):
rest at both ends, the analytic derivatives, the limits checked through the controller's own
allocation, the predicted Fisher information against an independent per-sample computation,
and the JSON round trip."""

import numpy as np
import pytest

from astrocargo.agents.controllers import CargoState, CooperativeController, RobotState
from astrocargo.agents.excitation import (
    TILT_DEPLOYED_RAD,
    DesignedTrajectory,
    ExcitationDesign,
    shipped_design,
    window,
    window_integral,
)
from astrocargo.agents.excitation_design import (
    DesignSettings,
    ExcitationDesigner,
    estimator_noise_terms,
)
from astrocargo.envs.sensors import estimator_noise_kwargs, noise_profile
from astrocargo.envs.world import World
from astrocargo.estimator.cargo_estimator import CargoEstimator, Instant, WrenchMessage
from astrocargo.estimator.motion import grasp_acc_map
from astrocargo.estimator.rne import (
    balance_motion_jacobians,
    body_regressor,
    grasp_from_base,
    grasp_pose,
    wrench_transform,
)

DT = 1.0 / 62.5


def _random_design(seed: int = 1, n_harm: int = 3, spin=(0.03, -0.02, 0.04)) -> ExcitationDesign:
    rng = np.random.default_rng(seed)
    coeffs = rng.normal(0.0, 0.05, (7, 2 * n_harm))
    return ExcitationDesign(coeffs, 30.0, 60.0, 8.0, 2, (0.1, -0.05, 0.0), spin_radps=spin)


@pytest.fixture(scope="module")
def model():
    from astrocargo.agents.excitation_design import model_for_world

    kwargs = estimator_noise_kwargs(noise_profile("nominal"))
    return model_for_world(World(2), estimator_kwargs=kwargs)


def test_design_starts_and_ends_at_rest():
    design = _random_design()
    traj = DesignedTrajectory(design)
    for t in (0.0, design.duration_s, design.duration_s + 5.0):
        ref = traj(t)
        for v in (ref.vel, ref.acc, ref.w, ref.wd):
            np.testing.assert_allclose(v, 0.0, atol=1e-12)
        assert abs(ref.pan) < 1e-12 and abs(ref.pan_rate) < 1e-12
        np.testing.assert_allclose(ref.pos, design.center_m, atol=1e-12)
    np.testing.assert_allclose(traj(0.0).rot, np.eye(3), atol=1e-12)
    # In between it moves.
    assert np.linalg.norm(traj(design.duration_s / 2).w) > 1e-3


def test_window_and_its_integral():
    t = np.linspace(-1.0, 61.0, 62001)
    s, sd, sdd = window(t, 60.0, 8.0)
    dt = t[1] - t[0]
    np.testing.assert_allclose(np.gradient(s, dt)[1:-1], sd[1:-1], atol=1e-4)
    np.testing.assert_allclose(np.gradient(sd, dt)[1:-1], sdd[1:-1], atol=1e-3)
    integral = np.concatenate(([0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * dt)))
    np.testing.assert_allclose(window_integral(t, 60.0, 8.0), integral, atol=1e-6)
    assert window_integral(np.array([60.0]), 60.0, 8.0)[0] == pytest.approx(52.0)


def test_analytic_rates_match_finite_differences():
    traj = DesignedTrajectory(_random_design())
    h = 1e-4
    for t in (7.0, 23.3, 41.9):
        m = traj.motion(np.array([t - h, t, t + h]))
        np.testing.assert_allclose((m.pos[2] - m.pos[0]) / (2 * h), m.vel[1], atol=1e-7)
        np.testing.assert_allclose((m.vel[2] - m.vel[0]) / (2 * h), m.acc[1], atol=1e-7)
        np.testing.assert_allclose((m.w[2] - m.w[0]) / (2 * h), m.wd[1], atol=1e-7)
        np.testing.assert_allclose((m.pan[2] - m.pan[0]) / (2 * h), m.pan_rate[1], atol=1e-7)
        # R' R^T = skew(w), world axes.
        rdot = (m.rot[2] - m.rot[0]) / (2 * h)
        sk = rdot @ m.rot[1].T
        np.testing.assert_allclose([sk[2, 1], sk[0, 2], sk[1, 0]], m.w[1], atol=1e-7)
        ref = traj(t)
        np.testing.assert_allclose(ref.rot, m.rot[1], atol=1e-15)
        np.testing.assert_allclose(ref.wd, m.wd[1], atol=1e-15)


def test_json_round_trip(tmp_path):
    design = _random_design()
    design = ExcitationDesign(
        design.coeffs, 30.0, 60.0, 8.0, 2, (0.1, -0.05, 0.0), {"predicted": [0.1]}, (0.1, 0, 0)
    )
    path = tmp_path / "d.json"
    design.save(path)
    back = ExcitationDesign.load(path)
    np.testing.assert_array_equal(back.coeffs, design.coeffs)
    assert (back.period_s, back.duration_s, back.ramp_s, back.n_robots) == (30.0, 60.0, 8.0, 2)
    assert back.center_m == design.center_m and back.spin_radps == design.spin_radps
    assert back.info == design.info
    path.write_text('{"kind": "other"}')
    with pytest.raises(ValueError, match="not an excitation design"):
        ExcitationDesign.load(path)
    with pytest.raises(ValueError, match="coeffs"):
        ExcitationDesign(np.zeros((6, 4)), 30.0, 60.0, 8.0, 2)


def _controller_commands(model, ref, pan: float) -> list[np.ndarray]:
    """Feed-forward commands through CooperativeController itself (no error, the design cargo),
    before its uniform scaling at saturation."""
    states = []
    for i in range(model.n_robots):
        rot_cb, pos_cb = model.base_in_cargo(i, pan)
        states.append(
            RobotState(
                ref.rot @ rot_cb, ref.pos + ref.rot @ pos_cb, np.array([TILT_DEPLOYED_RAD, pan])
            )
        )
    cargo = CargoState(ref.rot, ref.pos, ref.vel, ref.w)
    controller = CooperativeController(model.robots)
    commands = controller.commands(ref, cargo, states, model.cargo_params)
    return [u * max(controller.last_ratio, 1.0) for u in commands]


@pytest.mark.parametrize("n_robots", [1, 2, 3])
def test_shipped_design_respects_limits_through_the_allocation(model, n_robots):
    """Every shipped design (1, 2 and 3 robots) within its servo range and rate, its thrust
    margin through the controller's own allocation and its wall clearance."""
    from astrocargo.agents.excitation_design import model_for_world

    if n_robots != model.n_robots:
        model = model_for_world(
            World(n_robots), estimator_kwargs=estimator_noise_kwargs(noise_profile("nominal"))
        )
    design = shipped_design(n_robots)
    traj = DesignedTrajectory(design)
    lim = model.limits
    # Servo range and rate at the control rate.
    m = traj.motion(np.arange(0.0, design.duration_s + DT, DT))
    assert np.max(np.abs(m.pan)) <= lim.pan_range_rad + 1e-9
    assert np.max(np.abs(m.pan_rate)) <= lim.pan_rate_radps * (1 - lim.pan_rate_margin) + 1e-9
    # Thrust per axis through the controller's own allocation, every 0.25 s.
    worst = 0.0
    for t in np.arange(0.0, design.duration_s, 0.25):
        ref = traj(t)
        for u, robot in zip(_controller_commands(model, ref, ref.pan), model.robots, strict=True):
            worst = max(worst, float(np.max(np.abs(u) / robot.thrust_limit)))
    # Within the margin it was designed (or scaled) for, as its file records.
    margin = design.info.get("limits", {}).get("thrust_margin", lim.thrust_margin)
    assert 0.3 < worst <= (1 - margin) * 1.01
    # Wall clearance of the assembly's hull.
    reach = np.abs(m.pos[:, :, None] + m.rot @ model.hull.T).max(axis=2)
    assert np.all(reach + lim.clearance_m <= model.aisle_half * (1 + 1e-6))


def test_reference_bounds_score_a_trajectory_as_a_design(model):
    """``reference_bounds`` of a design flown as a reference (``reference_motion`` through
    ``traj(t)``) equals the designer's own score of that design, and a design scaled down
    moves less and gets wider bounds."""
    settings = DesignSettings(duration_s=40.0, n_harmonics=2, ramp_s=8.0)
    designer = ExcitationDesigner(model, settings)
    design = _random_design(n_harm=2)
    design = ExcitationDesign(design.coeffs * 0.3, 20.0, 40.0, 8.0, 2, spin_radps=(0.02, 0, 0))
    got = designer.reference_bounds(DesignedTrajectory(design))
    want = designer.evaluate(design)["bounds"]
    np.testing.assert_allclose(got["principal_rel"], want["principal_rel"], rtol=1e-6)
    assert got["mass_rel"] == pytest.approx(want["mass_rel"], rel=1e-6)
    small = design.scaled(0.5)
    assert small.info["scaled"] == 0.5 and small.spin_radps[0] == pytest.approx(0.01)
    np.testing.assert_array_equal(small.coeffs[6], design.coeffs[6])  # the pan stays
    wider = designer.evaluate(small)["bounds"]
    assert all(
        w > 1.5 * b for w, b in zip(wider["principal_rel"], want["principal_rel"], strict=True)
    )
    # Scored against the design's own bounds, the design's ratios are 1.
    mine = ExcitationDesigner(model, DesignSettings(**{**settings.__dict__, "targets": got}))
    np.testing.assert_allclose(mine.evaluate(design)["ratios"], 1.0, rtol=1e-6)
    with pytest.raises(ValueError, match="factor"):
        design.scaled(0.0)


def test_tabulated_allocation_matches_the_controller(model):
    traj = DesignedTrajectory(_random_design(n_harm=2))
    times = np.array([5.0, 17.0, 33.0, 49.0])
    cmd = model.commands(traj.motion(times))
    for k, t in enumerate(times):
        ref = traj(t)
        expected = np.stack(_controller_commands(model, ref, ref.pan))
        np.testing.assert_allclose(cmd[k], expected, rtol=2e-3, atol=2e-3 * np.abs(expected).max())


def test_predicted_fisher_equals_the_regressor_on_the_designs_motion(model):
    """The model's F against a per-sample computation from the Reference, the controller's
    commands and the estimator's noise pieces at each sample's own pan (no table)."""
    est = model.estimator
    traj = DesignedTrajectory(_random_design(n_harm=2))
    times = np.arange(4.0, 60.0, 0.8)
    rot_ch, pos_ch = model.handrails[0]
    fisher = np.zeros((10, 10))
    for t in times:
        ref = traj(t)
        rot_wg = ref.rot @ rot_ch
        p = ref.rot @ pos_ch
        acc = ref.acc + np.cross(ref.wd, p) + np.cross(ref.w, np.cross(ref.w, p))
        a = body_regressor(rot_wg.T @ acc, rot_wg.T @ ref.w, rot_wg.T @ ref.wd)
        cov = np.zeros((6, 6))
        for j, (robot, u) in enumerate(
            zip(model.robots, _controller_commands(model, ref, ref.pan), strict=True)
        ):
            rot_bg, pos_bg = grasp_pose(robot, np.array([TILT_DEPLOYED_RAD, ref.pan]))
            to_grasp = grasp_from_base(rot_bg, pos_bg) @ wrench_transform(
                robot.thrust_rot, robot.thrust_pos
            )
            if j:
                rot_j, pos_j = model.handrails[j]
                to_grasp = (
                    wrench_transform(rot_ch.T @ rot_j, rot_ch.T @ (pos_j - pos_ch)) @ to_grasp
                )
            std = np.repeat(est.actuation_noise[[0, 2]], 3) + np.repeat(
                est.actuation_noise[[1, 3]], 3
            ) * np.abs(u)
            cov += to_grasp @ np.diag(std**2) @ to_grasp.T
        motion_cov = estimator_noise_terms(
            est,
            model.robots,
            model.relative_grasps,
            model.cargo_grasp,
            np.array([TILT_DEPLOYED_RAD, ref.pan]),
        )["motion_cov"]
        r = est.meas_cov + cov / est.update_every + motion_cov
        fisher += a.T @ np.linalg.solve(r, a)
    predicted = model.fisher(traj.motion(times))
    np.testing.assert_allclose(predicted, fisher, rtol=5e-3, atol=5e-3 * np.abs(fisher).max())


def _team_estimators(n_robots: int, fusion: str):
    """Each robot's CargoEstimator of an n-robot team (the grasp layout known), as the env
    builds them, and the world."""
    world = World(n_robots)
    kwargs = {**estimator_noise_kwargs(noise_profile("nominal")), "motion_fusion": fusion}
    ests = []
    for i in range(n_robots):
        peers = [j for j in range(n_robots) if j != i]
        relative = {j: world.relative_grasp(i, j) for j in peers}
        ests.append(
            CargoEstimator(world.robot_model(i), i, peers, DT, relative_grasps=relative, **kwargs)
        )
    return world, ests


@pytest.mark.parametrize("n_robots, fusion", [(1, "team"), (2, "team"), (3, "team"), (2, "own")])
def test_motion_covariance_is_the_estimators(n_robots, fusion):
    """At a configuration, ``estimator_noise_terms``'s motion covariance equals the one the
    estimator itself builds (``CargoEstimator._balance_terms``) from instants and messages of
    robots moving arbitrarily (the covariance does not depend on the rates, the accelerations or
    the observed mismatch), and it is not the scalar model of ``motion_fusion="none"``."""
    from astrocargo.agents.excitation_design import model_for_world

    world, ests = _team_estimators(n_robots, fusion)
    kwargs = {**estimator_noise_kwargs(noise_profile("nominal")), "motion_fusion": fusion}
    model = model_for_world(world, estimator_kwargs=kwargs)
    est = ests[0]
    est.ukf.x = model.cargo_grasp.copy()  # the estimate at the design cargo
    rng = np.random.default_rng(3)
    q = np.array([TILT_DEPLOYED_RAD, 0.23])
    msgs, inst = [], None
    for i, e in enumerate(ests):
        w, wd, acc, qd, qdd = (rng.normal(0.0, 0.05, k) for k in (3, 3, 3, 2, 2))
        d_links, d_y = balance_motion_jacobians(e.robot, w, wd, acc, q, qd, qdd)
        if i == 0:
            inst = Instant(
                np.zeros(6), np.zeros(6), rng.normal(size=(6, 10)), np.zeros((6, 6)), False,
                (d_links, d_y),
            )  # fmt: skip
            continue
        msgs.append(
            WrenchMessage(
                i, 0, np.zeros(6), np.zeros(6), np.zeros(3), np.eye(3), False, np.zeros((6, 6)),
                grasp_acc=rng.normal(0.0, 0.01, 3), motion_links_jac=d_links,
                motion_grasp_jac=grasp_acc_map(d_y), motion_var=e.noise.motion.var,
                motion_band=e.noise.motion.band,
            )
        )  # fmt: skip
    # The designer plans with the acceleration form's motion noise (``NoiseModel.motion``), the
    # estimator's own model of that configuration before the momentum chain's.
    peers = [(est._relative[p].transform(), m) for p, m in zip(est.peers, msgs, strict=True)]
    _, expected = est.noise.motion_noise(
        est.motion_fusion, est.ukf.params_mean(), inst.motion_jac, inst.regressor, peers,
        est._grasp_lever,
    )  # fmt: skip
    terms = estimator_noise_terms(
        model.estimator, model.robots, model.relative_grasps, model.cargo_grasp, q
    )
    np.testing.assert_allclose(
        terms["motion_cov"], expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max()
    )
    np.testing.assert_allclose(terms["meas_cov"], est.meas_cov, rtol=1e-12)
    # The designer's table at that pan holds it too.
    np.testing.assert_allclose(
        model.team(np.array([0.23]))["motion_cov"][0],
        expected,
        rtol=0.05,
        atol=0.05 * np.abs(expected).max(),
    )
    scalar = est.sensor_cov_at(model.cargo_grasp, np.linalg.norm(grasp_pose(est.robot, q)[1]))
    assert np.abs(terms["motion_cov"] - scalar).max() > 0.1 * np.abs(scalar).max()


def test_designer_improves_on_its_start(model):
    """A short design run ends feasible on a dense grid and beats its own random start made
    feasible by scaling."""
    settings = DesignSettings(duration_s=40.0, n_harmonics=2, ramp_s=8.0, starts=1, maxiter=15)
    designer = ExcitationDesigner(model, settings)
    x0 = np.random.default_rng(settings.seed).normal(0.0, settings.start_std, designer.n_vars)
    x0_feasible, _ = designer._feasible_scale(x0 * designer.free())
    start_worst = np.max(designer.evaluate(designer.design_of(x0_feasible))["ratios"])
    design = designer.run()
    assert max(design.info["max_violation"].values()) <= 1e-9
    found_worst = np.max(designer.evaluate(design)["ratios"])
    assert found_worst < 0.9 * start_worst
    assert set(design.info["predicted_bounds"]) >= {"mass_rel", "com_m", "principal_rel"}


def test_make_trajectory_names(tmp_path):
    from astrocargo.agents.excitation import make_trajectory
    from astrocargo.agents.trajectories import Trajectory

    assert isinstance(make_trajectory("figure8_tumble", 2), Trajectory)
    excite = make_trajectory("excite", 2)
    assert isinstance(excite, DesignedTrajectory) and excite.design.n_robots == 2
    path = tmp_path / "mine.json"
    _random_design().save(path)
    mine = make_trajectory(str(path), 2)
    np.testing.assert_array_equal(mine.design.coeffs, _random_design().coeffs)
    with pytest.raises(ValueError, match="designed for 2 robots"):
        make_trajectory(str(path), 3)
    with pytest.raises(ValueError, match="unknown trajectory"):
        make_trajectory("loop", 2)
    with pytest.raises(ValueError, match="fast"):
        make_trajectory("excite", 2, fast=True)
    with pytest.raises(ValueError, match="no excitation design shipped"):
        make_trajectory("excite", 7)  # none shipped, and no world to design one for


def test_env_flies_the_shipped_design_and_a_design_file(tmp_path):
    """trajectory="excite" gives the shipped design for the team (its reference, pan included,
    is what the env observes and steps on); a design file path flies that design."""
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(n_robots=2, trajectory="excite", max_cycles=5)
    env.reset(seed=0)
    assert isinstance(env.sim.trajectory, DesignedTrajectory)
    for _ in range(3):
        env.step({a: np.zeros(8) for a in env.agents})
    ref, want = env.sim.reference(), env.sim.trajectory(env.sim.data.time)
    np.testing.assert_array_equal(ref.pos, want.pos)
    assert env.sim.data.time > 0
    path = tmp_path / "mine.json"
    _random_design().save(path)
    env = astrobee_cargo_v0.parallel_env(n_robots=2, trajectory=str(path), max_cycles=5)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.sim.trajectory.design.coeffs, _random_design().coeffs)


@pytest.mark.parametrize(
    "trajectory, message",
    [
        ("nowhere/design.json", "'nowhere/design.json' does not exist"),
        ("circle", "unknown trajectory 'circle'"),
    ],
)
def test_env_rejects_a_bad_trajectory(tmp_path, trajectory, message):
    from astrocargo.envs import astrobee_cargo_v0

    with pytest.raises(ValueError, match=message):
        astrobee_cargo_v0.parallel_env(n_robots=2, trajectory=trajectory)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="is not a design"):
        astrobee_cargo_v0.parallel_env(n_robots=2, trajectory=str(bad))
    with pytest.raises(ValueError, match="fast=True"):
        astrobee_cargo_v0.parallel_env(n_robots=2, trajectory="excite", fast=True)


def test_designed_trajectory_arrays_hold_the_reference():
    """``arrays(t)`` (what the env evaluates each step) holds the numbers of ``traj(t)``."""
    from astrocargo.agents.excitation import DESIGNS_DIR, DesignedTrajectory, ExcitationDesign

    traj = DesignedTrajectory(ExcitationDesign.load(DESIGNS_DIR / "excite_2robots.json"))
    for t in (0.0, 13.7, 45.0, 89.9, 120.0):
        rot, vecs, pan = traj.arrays(t)
        ref = traj(t)
        np.testing.assert_allclose(rot, ref.rot, atol=1e-15)
        np.testing.assert_allclose(vecs, [ref.pos, ref.vel, ref.acc, ref.w, ref.wd], atol=1e-15)
        np.testing.assert_allclose(pan, [ref.pan, ref.pan_rate], atol=1e-15)
