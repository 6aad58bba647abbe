"""Reference check of the sub-body Newton-Euler model against MuJoCo's own dynamics.

In the world with 1 to 4 robots, under random propulsion and arm motion, with the true cargo and
exact kinematics read from MuJoCo, each robot's model must reproduce
  - the propulsion wrench MuJoCo applied (thrust = own links + cargo - peers' wrenches), and
  - the wrench MuJoCo transmits at its grasp (``cfrc_int`` of the gripper, the tree's joint force).
The model is exact for the rigid tree the world builds, so the tolerances are far below the
issue's bounds (0.5 % of the propulsion limits, 1 % of the grasp wrench): a sign or frame error
anywhere shows up as an O(1) error.
"""

import mujoco
import numpy as np
import pytest

from astrocargo.envs.world import World
from astrocargo.estimator import rne
from astrocargo.estimator.inertia import transform_params

THRUST_TOL = 1e-9  # of the propulsion limit, per axis
GRASP_TOL = 1e-9  # relative to the grasp wrench norm


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, q)
    return mat.reshape(3, 3)


def _base_motion(model, data, body):
    """Angular velocity, angular acceleration and origin acceleration of a body, body frame."""
    vel = np.zeros(6)
    acc = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, vel, 1)
    mujoco.mj_objectAcceleration(model, data, mujoco.mjtObj.mjOBJ_XBODY, body, acc, 1)
    return vel[:3], acc[:3], acc[3:]


def _cargo_params_in_grasp_frames(world):
    params = world.cargo_params()
    out = []
    for h in world.robots:
        s = h.cargo_grasp_site
        rot = _quat_to_mat(world.model.site_quat[s])
        out.append(transform_params(params, rot.T, -rot.T @ world.model.site_pos[s]))
    return out


def _run(n_robots: int, seconds: float = 6.0, seed: int = 0):
    world = World(n_robots)
    model = world.model
    data = world.make_data()
    world.set_cargo(
        4.2,
        (0.03, -0.02, 0.05),
        np.array([[0.08, 0.01, -0.005], [0.01, 0.11, 0.004], [-0.005, 0.004, 0.12]]),
    )
    mujoco.mj_forward(model, data)
    rng = np.random.default_rng(seed)
    limit = world.robot_model(0).thrust_limit
    cargo_pi = _cargo_params_in_grasp_frames(world)
    thrust_err, grasp_err = [], []
    n_sub = 8  # one 62.5 Hz control period
    for period in range(int(seconds / (n_sub * model.opt.timestep))):
        t = period * n_sub * model.opt.timestep
        for h in world.robots:
            data.ctrl[list(h.thrust_actuators)] = rng.uniform(-1, 1, 6) * limit
            data.ctrl[list(h.arm_actuators)] = [
                -np.pi / 2 + 0.5 * np.sin(0.7 * t + h.index),
                0.6 * np.sin(0.5 * t + 2 * h.index),
            ]
        mujoco.mj_step(model, data, nstep=n_sub)
        mujoco.mj_forward(model, data)
        mujoco.mj_rnePostConstraint(model, data)
        per_robot = []
        for h in world.robots:
            robot = world.robot_model(h.index)
            kin = rne.propagate(
                robot,
                *_base_motion(model, data, h.base_body),
                data.qpos[list(h.arm_qpos_adr)],
                data.qvel[list(h.arm_dof_adr)],
                data.qacc[list(h.arm_dof_adr)],
            )
            to_world = rne.wrench_transform(
                data.xmat[h.base_body].reshape(3, 3), data.xpos[h.base_body]
            )
            thrust = rne.thrust_wrench(robot, data.actuator_force[list(h.thrust_actuators)])
            links = rne.link_momentum_rate(robot, kin)
            cargo = rne.cargo_regressor(kin) @ cargo_pi[h.index]
            per_robot.append((to_world, thrust, links, cargo))
        for i, (to_world, thrust, links, cargo) in enumerate(per_robot):
            peers_world = sum(
                (tw @ (th - lk) for j, (tw, th, lk, _) in enumerate(per_robot) if j != i),
                np.zeros(6),
            )
            peers = np.linalg.solve(to_world, peers_world)
            thrust_err.append((links + cargo - peers - thrust) / limit)
            # Wrench robot i applies to the cargo vs the force MuJoCo transmits at the grasp.
            # cfrc_int of the gripper ([torque; force] about the tree root's subtree centre of
            # mass, world axes) is the rate of change of momentum of robot i's whole subtree from
            # MuJoCo's own accelerations; actuator forces enter MuJoCo through joint space, not
            # cfrc_ext, so the force the cargo exerts on the robot is that minus the thrust.
            h = world.robots[i]
            gripper = h.link_bodies[-1]
            root = model.body_rootid[gripper]
            to_root = rne.wrench_transform(np.eye(3), -data.subtree_com[root])
            mine = to_root @ to_world @ (thrust - links)
            subtree_rate = np.concatenate((data.cfrc_int[gripper][3:], data.cfrc_int[gripper][:3]))
            mj = to_root @ to_world @ thrust - subtree_rate
            grasp_err.append(np.linalg.norm(mine - mj) / np.linalg.norm(mj))
    return np.abs(np.array(thrust_err)), np.array(grasp_err), data


@pytest.mark.parametrize("n_robots", [1, 2, 3])
def test_model_reproduces_mujoco(n_robots):
    thrust_err, grasp_err, data = _run(n_robots)
    assert np.all(np.isfinite(thrust_err))
    assert data.ncon == 0, "robots touched something: the check assumes no contact forces"
    assert thrust_err.max() < THRUST_TOL, f"thrust error / limit per axis {thrust_err.max(0)}"
    assert grasp_err.max() < GRASP_TOL, f"grasp wrench relative error {grasp_err.max()}"


def test_check_detects_wrong_cargo():
    """The same check with a 1 % heavier cargo model must fail by far: the test can fail."""
    world = World(1)
    model, data = world.model, world.make_data()
    h = world.robots[0]
    robot = world.robot_model(0)
    pi = _cargo_params_in_grasp_frames(world)[0]
    data.ctrl[list(h.thrust_actuators)] = robot.thrust_limit
    mujoco.mj_step(model, data, nstep=50)
    mujoco.mj_forward(model, data)
    kin = rne.propagate(
        robot,
        *_base_motion(model, data, h.base_body),
        data.qpos[list(h.arm_qpos_adr)],
        data.qvel[list(h.arm_dof_adr)],
        data.qacc[list(h.arm_dof_adr)],
    )
    thrust = rne.thrust_wrench(robot, data.actuator_force[list(h.thrust_actuators)])
    links = rne.link_momentum_rate(robot, kin)
    wrong = pi * 1.01
    err_ok = np.abs(links + rne.cargo_regressor(kin) @ pi - thrust) / robot.thrust_limit
    err_bad = np.abs(links + rne.cargo_regressor(kin) @ wrong - thrust) / robot.thrust_limit
    assert err_ok.max() < THRUST_TOL
    assert err_bad.max() > 1e-4
