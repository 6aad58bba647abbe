"""Reference trajectories (limits, derivatives, module margins), the team's rigid-body kernels
(composite body, allocation) against the estimator's own models, and the cooperative controllers
(hold a hover, track a step; the observation-driven one equals the state-driven one)."""

import dataclasses

import mujoco
import numpy as np
import pytest
from true_state import true_states

from astrocargo.agents.controllers import (
    CargoState,
    CooperativeController,
    ObservationController,
    RobotState,
)
from astrocargo.agents.team_dynamics import (
    ARM_STEP_S,
    allocate,
    robot_body,
    team_model,
    wrench_map,
)
from astrocargo.agents.trajectories import (
    FAST_ACCEL_MPS2,
    NOMINAL_ACCEL_MPS2,
    NOMINAL_RATE_RADPS,
    NOMINAL_SPEED_MPS,
    Reference,
    Trajectory,
)
from astrocargo.envs import astrobee_cargo_v0
from astrocargo.envs.world import World
from astrocargo.estimator.geometry import exp_so3, log_so3
from astrocargo.estimator.inertia import (
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    transform_params,
)
from astrocargo.estimator.rne import grasp_pose, link_poses, wrench_transform

DT = 0.01
TIMES = np.arange(0.0, 130.0, DT)


def _sample(name, fast=False):
    tr = Trajectory(name, fast=fast)
    return [tr(t) for t in TIMES]


@pytest.mark.parametrize("name", ["figure8_yaw", "figure8_tumble"])
@pytest.mark.parametrize("fast", [False, True])
def test_limits_hold(name, fast):
    refs = _sample(name, fast)
    speed = max(np.linalg.norm(r.vel) for r in refs)
    accel = max(np.linalg.norm(r.acc) for r in refs)
    rate = max(np.linalg.norm(r.w) for r in refs)
    assert speed <= NOMINAL_SPEED_MPS
    assert accel <= (FAST_ACCEL_MPS2 if fast else NOMINAL_ACCEL_MPS2)
    assert rate <= NOMINAL_RATE_RADPS
    # Inside the 6 x 2.2 x 2.2 m aisle with margin for the robots around the cargo (~0.8 m).
    pos = np.array([r.pos for r in refs])
    assert np.all(np.abs(pos[:, 0]) < 3.0 - 1.0)
    assert np.all(np.abs(pos[:, 1:]) < 1.1 - 0.8)


@pytest.mark.parametrize("name", ["figure8_yaw", "figure8_tumble", "hover"])
def test_derivatives_are_consistent(name):
    refs = _sample(name)
    pos = np.array([r.pos for r in refs])
    vel = np.array([r.vel for r in refs])
    acc = np.array([r.acc for r in refs])
    w = np.array([r.w for r in refs])
    wd = np.array([r.wd for r in refs])
    mid = lambda x: 0.5 * (x[1:] + x[:-1])  # noqa: E731
    np.testing.assert_allclose(np.diff(pos, axis=0) / DT, mid(vel), atol=1e-6)
    np.testing.assert_allclose(np.diff(vel, axis=0) / DT, mid(acc), atol=1e-6)
    np.testing.assert_allclose(np.diff(w, axis=0) / DT, mid(wd), atol=1e-5)
    # Angular velocity (world axes) from consecutive attitudes.
    fd_w = np.array(
        [log_so3(b.rot @ a.rot.T) / DT for a, b in zip(refs[:-1], refs[1:], strict=True)]
    )
    np.testing.assert_allclose(fd_w, mid(w), atol=1e-6)
    pan = np.array([r.pan for r in refs])
    pan_rate = np.array([r.pan_rate for r in refs])
    smooth = np.abs(np.diff(pan_rate)) < 1e-3  # away from the triangle's corners
    np.testing.assert_allclose((np.diff(pan) / DT)[smooth], mid(pan_rate)[smooth], atol=1e-6)


def test_tumble_rotates_about_three_axes_and_yaw_about_one():
    yaw = np.array([r.w for r in _sample("figure8_yaw")])
    tumble = np.array([r.w for r in _sample("figure8_tumble")])
    assert np.abs(yaw[:, :2]).max() < 1e-12
    assert np.all(np.abs(tumble).max(axis=0) > 0.04)


@pytest.mark.parametrize("name", Trajectory.NAMES)
def test_arrays_are_the_reference_packed(name):
    """``arrays(t)`` (what the env evaluates each step) holds the very numbers of ``tr(t)``."""
    tr = Trajectory(name)
    for t in (0.0, 7.3, 15.0, 42.5, 61.2):
        ref, (rot, vecs, pan) = tr(t), tr.arrays(t)
        np.testing.assert_array_equal(rot, ref.rot)
        np.testing.assert_array_equal(vecs, [ref.pos, ref.vel, ref.acc, ref.w, ref.wd])
        np.testing.assert_array_equal(pan, [ref.pan, ref.pan_rate])


def test_unknown_trajectory():
    with pytest.raises(ValueError, match="allowed"):
        Trajectory("figure9")


def _run_controller(world, data, ref_fn, seconds):
    model = world.model
    controller = CooperativeController([world.robot_model(i) for i in range(world.n_robots)])
    truth = world.cargo_params()
    nsub = round(0.016 / model.opt.timestep)
    errors = []
    for k in range(int(seconds / 0.016)):
        ref = ref_fn(k * 0.016)
        cargo, states = true_states(world, data)
        commands = controller.commands(ref, cargo, states, truth)
        for h, cmd, robot in zip(world.robots, commands, controller.robots, strict=True):
            assert np.all(np.abs(cmd) <= robot.thrust_limit + 1e-12)
            data.ctrl[list(h.thrust_actuators)] = cmd
        mujoco.mj_step(model, data, nstep=nsub)
        errors.append(
            (
                np.linalg.norm(ref.pos - cargo.pos),
                np.linalg.norm(log_so3(ref.rot @ cargo.rot.T)),
            )
        )
    return np.array(errors)


def test_controller_holds_a_hover_from_a_perturbed_start():
    world = World(2)
    data = world.make_data()
    data.qvel[world.cargo_qvel_adr : world.cargo_qvel_adr + 6] = [
        0.02,
        -0.01,
        0.01,
        0.02,
        -0.02,
        0.03,
    ]
    mujoco.mj_forward(world.model, data)
    errors = _run_controller(world, data, Trajectory("hover"), 40.0)
    assert errors[:, 0].max() > 0.005  # the kick moved it
    assert errors[-1, 0] < 2e-3 and errors[-1, 1] < np.deg2rad(0.5)


def test_controller_tracks_a_step():
    world = World(1)
    data = world.make_data()
    hover = Trajectory("hover")
    step = np.array([0.1, -0.05, 0.05])

    def ref_fn(t):
        r = hover(t)
        return type(r)(r.pos + step, r.vel, r.acc, r.rot, r.w, r.wd, r.pan, r.pan_rate)

    errors = _run_controller(world, data, ref_fn, 40.0)
    # PD with w_n = 0.77 rad/s, zeta = 0.77, saturating at first: settled within 2 cm in 20 s and
    # 2 mm in 40 s, without a large overshoot.
    assert errors[int(20 / 0.016), 0] < 0.02
    assert errors[-1, 0] < 2e-3
    assert errors[int(5 / 0.016) :, 0].max() < np.linalg.norm(step) * 1.2


# --------------------------------------------------------------------------- team kernels


def _robot_params_in_base(robot, q):
    """A robot's standard parameters (all links) in its base frame, from the estimator's
    forward kinematics and frame change."""
    rots, poss = link_poses(robot, q)
    links = np.stack(
        [params_from_mass_com_inertia(k.mass, k.com, k.inertia_com) for k in robot.links]
    )
    return transform_params(links, rots, poss).sum(axis=0)


def test_robot_body_is_the_estimator_model():
    """One robot's composite body and grasp frame at random arm angles equal the sum of its
    links' standard parameters (estimator.inertia) and rne's grasp pose."""
    world = World(1)
    robot = world.robot_model(0)
    team = team_model([robot])
    for q in np.random.default_rng(0).uniform(-2.0, 2.0, (5, robot.n_joints)):
        mass, com, inertia, rot_g, pos_g = robot_body(team, 0, q)
        want_mass, want_com, want_inertia = mass_com_inertia_from_params(
            _robot_params_in_base(robot, q)
        )
        np.testing.assert_allclose(mass, want_mass, rtol=1e-13)
        np.testing.assert_allclose(com, want_com, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(inertia, want_inertia, rtol=1e-11, atol=1e-15)
        want_rot, want_pos = grasp_pose(robot, q)
        np.testing.assert_allclose(rot_g, want_rot, atol=1e-14)
        np.testing.assert_allclose(pos_g, want_pos, atol=1e-14)


def _random_team(n, seed):
    rng = np.random.default_rng(seed)
    rot = np.stack([exp_so3(v) for v in rng.normal(size=(n, 3))])
    return rot, rng.normal(scale=0.5, size=(n, 3)), rng


def test_allocation_is_the_weighted_minimum_norm_solution():
    """Unsaturated: the commands deliver the wrench (sum G_j u_j) and equal the weighted
    pseudo-inverse W G^T (G W G^T)^-1 w over the robots holding; a robot not holding gets 0."""
    robots = [World(3).robot_model(i) for i in range(3)]
    team = team_model(robots)
    rot, pos, rng = _random_team(3, 1)
    com = rng.normal(scale=0.1, size=3)
    wrench = 1e-3 * rng.normal(size=6)
    holding = np.array([0, 2])
    cmds, ratio = allocate(team, holding, rot, pos, com, wrench)
    assert ratio < 1.0
    np.testing.assert_array_equal(cmds[1], np.zeros(6))
    g = np.hstack([wrench_transform(rot[j], pos[j] - com) for j in holding])
    w = np.diag(np.concatenate([robots[j].thrust_limit ** 2 for j in holding]))
    want = w @ g.T @ np.linalg.solve(g @ w @ g.T, wrench)
    np.testing.assert_allclose(cmds[holding].ravel(), want, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(g @ cmds[holding].ravel(), wrench, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(wrench_map(rot[0], pos[0] - com), g[:, :6], rtol=1e-15)


def test_saturated_allocation_keeps_the_direction():
    """A wrench beyond the limits: every command within its limit, one at it, and the delivered
    wrench a positive multiple of the requested one."""
    robots = [World(2).robot_model(i) for i in range(2)]
    team = team_model(robots)
    rot, pos, rng = _random_team(2, 2)
    wrench = 10.0 * rng.normal(size=6)
    cmds, ratio = allocate(team, np.array([0, 1]), rot, pos, np.zeros(3), wrench)
    assert ratio > 1.0
    usage = np.abs(cmds) / team.thrust_limit
    assert usage.max() == pytest.approx(1.0, rel=1e-12)
    delivered = sum(wrench_map(rot[j], pos[j]) @ cmds[j] for j in range(2))
    np.testing.assert_allclose(delivered * ratio, wrench, rtol=1e-10)


def test_team_model_shares_equal_robots_and_rejects_mixed_arms():
    world = World(3)
    robots = [world.robot_model(i) for i in range(3)]
    assert team_model(robots).model_of.tolist() == [0, 0, 0]
    base = dataclasses.replace(robots[1].links[0], mass=robots[1].links[0].mass + 1.0)
    heavier = dataclasses.replace(robots[1], links=(base, *robots[1].links[1:]))
    assert team_model([robots[0], heavier, robots[2]]).model_of.tolist() == [0, 1, 0]
    armless = dataclasses.replace(robots[1], links=robots[1].links[:1], grasp_link=0)
    with pytest.raises(ValueError, match="same number of links"):
        team_model([robots[0], armless])


# --------------------------------------------------------------------------- controllers


def _textbook_commands(robots, gains, ref, cargo, states, cargo_params):
    """The cooperative law written out with the estimator's numpy functions: composite standard
    parameters, PD + feed-forward wrench about the centre of mass, weighted minimum norm."""
    kp, kd, akp, akd = gains
    holding = [i for i, st in enumerate(states) if st is not None]
    total = transform_params(cargo_params, cargo.rot, cargo.pos)
    for i in holding:
        params = _robot_params_in_base(robots[i], states[i].joint_pos)
        total = total + transform_params(params, states[i].rot, states[i].pos)
    mass, com, inertia = mass_com_inertia_from_params(total)
    acc = ref.acc + kd * (ref.vel - cargo.vel) + kp * (ref.pos - cargo.pos)
    wd = ref.wd + akd * (ref.w - cargo.w) + akp * log_so3(ref.rot @ cargo.rot.T)
    r, w = com - cargo.pos, cargo.w
    force = mass * (acc + np.cross(wd, r) + np.cross(w, np.cross(w, r)))
    wrench = np.concatenate((force, inertia @ wd + np.cross(w, inertia @ w)))
    g = [wrench_transform(states[i].rot, states[i].pos - com) for i in holding]
    wgt = [np.diag(robots[i].thrust_limit ** 2) for i in holding]
    lam = np.linalg.solve(sum(a @ b @ a.T for a, b in zip(g, wgt, strict=True)), wrench)
    cmds = [b @ a.T @ lam for a, b in zip(g, wgt, strict=True)]
    ratio = max(
        np.max(np.abs(u) / robots[i].thrust_limit) for u, i in zip(cmds, holding, strict=True)
    )
    out = [np.zeros(6) for _ in robots]
    for i, u in zip(holding, cmds, strict=True):
        out[i] = u / max(ratio, 1.0)
    return out


def test_cooperative_controller_is_the_textbook_law():
    """On a kicked three-robot team, with one robot let go, the compiled controller equals the
    law written out with the estimator's functions."""
    env = astrobee_cargo_v0.parallel_env(n_robots=3, trajectory="figure8_tumble")
    env.reset(seed=0)
    sim = env.sim
    controller = ObservationController.for_env(env, "truth")
    obs = None
    for _ in range(40):
        obs = env.step(controller.predict(obs)[0] if obs else {a: np.zeros(8) for a in env.agents})[
            0
        ]
    cargo, states = true_states(sim.world, sim.data)
    ref = sim.reference()
    team = CooperativeController(sim.robots)
    for holding in ([0, 1, 2], [0, 2]):
        st = [s if i in holding else None for i, s in enumerate(states)]
        got = team.commands(ref, cargo, st, sim.true_params)
        want = _textbook_commands(sim.robots, team.gains, ref, cargo, st, sim.true_params)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-14)


def _team_arms_seen(ctrl, i, o):
    """Every robot's arm angles and rates as robot i's observation gives them: its own encoders
    and servo-target rates; a peer's from its latest message, q + qd * age (own before one)."""
    lay, n = ctrl.layout, len(ctrl.robots)
    q = [o[lay["joint_pos"]].copy() for _ in range(n)]
    qd = [o[lay["joint_vel"]].copy() for _ in range(n)]
    for p, j in enumerate(j for j in range(n) if j != i):
        if o[lay[f"peer{p}_valid"]][0] == 1.0:
            qd[j] = o[lay[f"peer{p}_joint_vel"]]
            q[j] = o[lay[f"peer{p}_joint_pos"]] + qd[j] * o[lay[f"peer{p}_age"]][0]
    return q, qd


def _base_in_cargo(ctrl, j, q):
    rot_bg, pos_bg = grasp_pose(ctrl.robots[j], q)
    rot_ch, pos_ch = ctrl.handrail_poses[j]
    rot_cb = rot_ch @ rot_bg.T
    return rot_cb, pos_ch - rot_cb @ pos_bg


def _state_driven_action(ctrl, i, o, holding):
    """Robot i's action by ``CooperativeController`` on the state robot i sees, in the cargo
    frame C: every robot at the arm angles and rates it sees, the cargo at rest at C's origin
    turning at robot i's gyro rate less its base's rate relative to the cargo (central
    differences of the grasp pose over ARM_STEP_S), and a reference whose errors relative to it
    are the base's rotated into C (R_ref = exp(-R_cb e))."""
    lay = ctrl.layout
    q, qd = _team_arms_seen(ctrl, i, o)
    h = ARM_STEP_S
    (rot_up, pos_up), (rot, pos), (rot_down, pos_down) = (
        _base_in_cargo(ctrl, i, q[i] + s * qd[i] * h) for s in (1, 0, -1)
    )
    w_rel = 0.5 * (log_so3(rot_up @ rot.T) + log_so3(rot @ rot_down.T)) / h
    v_rel = (pos_up - pos_down) / (2 * h)
    w = rot @ o[lay["base_ang_vel"]] - w_rel
    vel_err = rot @ o[lay["base_vel_err"]] - v_rel
    states = [None] * len(ctrl.robots)
    for j in holding:
        states[j] = RobotState(*_base_in_cargo(ctrl, j, q[j]), q[j], qd[j])
    pan = o[lay["ref_pan"]]
    ref = Reference(
        -rot @ o[lay["base_pos_err"]],
        -vel_err,
        rot @ o[lay["ref_acc"]],
        exp_so3(-rot @ o[lay["base_att_err"]]),
        rot @ o[lay["ref_ang_vel"]],
        rot @ o[lay["ref_ang_acc"]],
        pan[0],
        pan[1],
    )
    cargo = CargoState(np.eye(3), np.zeros(3), np.zeros(3), w)
    params = {"none": None, "truth": ctrl.truth_params}.get(ctrl.cargo_model)
    if ctrl.cargo_model == "estimate":
        params = transform_params(o[lay["estimate_mean"]], *ctrl.handrail_poses[i])
    thrust = CooperativeController(ctrl.robots).commands(ref, cargo, states, params)[i]
    return np.concatenate(
        (thrust / ctrl.robots[i].thrust_limit, [0.0, np.clip(pan[0] / 0.5, -1, 1)])
    )


@pytest.mark.parametrize("cargo_model", ["estimate", "truth", "none"])
def test_observation_controller_is_the_state_driven_law(cargo_model):
    """Three robots after a kicked start: each robot's action from its observation equals the
    state-driven controller on the team it sees, for the dict of all agents, a dict of two (the
    third let go) and the array form."""
    env = astrobee_cargo_v0.parallel_env(n_robots=3, trajectory="figure8_tumble")
    obs, _ = env.reset(seed=1)
    ctrl = ObservationController.for_env(env, cargo_model, scale_down=True)
    rng = np.random.default_rng(0)
    for _ in range(260):
        obs = env.step({a: rng.uniform(-0.3, 0.3, 8) for a in env.agents})[0]
    agents = env.possible_agents
    lay = ctrl.layout
    # The peers' arms come from their messages, and they move.
    assert all(obs[a][lay["peer1_valid"]][0] == 1.0 for a in agents)
    assert all(np.abs(obs[a][lay["peer1_joint_vel"]]).max() > 0.01 for a in agents)
    unscaled = ObservationController.for_env(env, cargo_model)
    for subset in (agents, [agents[0], agents[2]]):
        actions, _ = ctrl.predict({a: obs[a] for a in subset})
        holding = [agents.index(a) for a in subset]
        for a in subset:
            want = _state_driven_action(ctrl, agents.index(a), obs[a], holding)
            np.testing.assert_allclose(actions[a], want, rtol=1e-9, atol=1e-13)
        # By default the allocation goes out unscaled: the env clips.
        raw, _ = unscaled.predict({a: obs[a] for a in subset})
        for a, ratio in zip(subset, ctrl.last_ratios, strict=True):
            np.testing.assert_allclose(raw[a][:6], actions[a][:6] * max(ratio, 1.0), rtol=1e-12)
    stacked, _ = ctrl.predict(np.stack([obs[a] for a in agents]))
    np.testing.assert_array_equal(stacked, np.stack([ctrl.predict(obs)[0][a] for a in agents]))


def test_observation_controller_rejects_bad_input():
    env = astrobee_cargo_v0.parallel_env(n_robots=2, observe_estimates=False)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match="observe_estimates"):
        ObservationController.for_env(env, "estimate")
    ctrl = ObservationController.for_env(env, "none")
    with pytest.raises(ValueError, match="unknown agents"):
        ctrl.predict({"astrobee_7": obs["astrobee_0"]})
    with pytest.raises(ValueError, match="shape"):
        ctrl.predict(np.zeros((3, 5)))


def test_controller_keeps_the_cargo_with_oscillating_arms():
    """figure8_tumble, 2 robots, with every arm's pan (+-0.2 rad, 10 s) and tilt (+-0.2 rad,
    14 s) oscillating on top of the pan ramp: the controller, following the peers' arms and
    their motion, keeps the cargo off the walls for 60 s (main's controller, which put every arm
    at the robot's own angles and the assembly rigid, hit a wall at 51 s; with its wrench scaled
    down uniformly this one hits one at 49 s); ``saturated`` is in infos, in [0, 1], and shows
    the saturation the arms cause."""
    env = astrobee_cargo_v0.parallel_env(
        n_robots=2, trajectory="figure8_tumble", max_cycles=int(60 * 62.5)
    )
    obs, _ = env.reset(seed=0)
    ctrl = ObservationController.for_env(env, "estimate")
    saturated, infos = [], {}
    while env.agents:
        actions, _ = ctrl.predict(obs)
        t = env.sim.data.time
        for k, a in enumerate(env.agents):
            actions[a][7] = np.clip(actions[a][7] + 0.4 * np.sin(2 * np.pi * t / 10 + k), -1, 1)
            actions[a][6] = 0.4 * np.sin(2 * np.pi * t / 14 + 2 * k)
        obs, _, _, _, infos = env.step(actions)
        saturated += [info["saturated"] for info in infos.values()]
    assert next(iter(infos.values()))["termination_reason"] is None
    assert env.sim.data.time == pytest.approx(60.0, abs=0.02)
    saturated = np.array(saturated)
    assert np.all((saturated >= 0) & (saturated <= 1))
    assert saturated.max() > 0.1
