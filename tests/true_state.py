"""The cargo's and robots' true state read from MuJoCo, for tests that drive the controller on
the truth (the env's job, done directly so a module can be tested on its own)."""

import mujoco
import numpy as np

from astrocargo.agents.controllers import CargoState, RobotState


def true_states(world, data) -> tuple[CargoState, list[RobotState]]:
    """Cargo frame pose and twist (world axes) and every robot's base pose and arm angles."""
    b = world.cargo_body
    vel = np.zeros(6)
    mujoco.mj_objectVelocity(world.model, data, mujoco.mjtObj.mjOBJ_XBODY, b, vel, 0)
    cargo = CargoState(data.xmat[b].reshape(3, 3).copy(), data.xpos[b].copy(), vel[3:], vel[:3])
    robots = [
        RobotState(
            data.xmat[h.base_body].reshape(3, 3).copy(),
            data.xpos[h.base_body].copy(),
            data.qpos[list(h.arm_qpos_adr)].copy(),
        )
        for h in world.robots
    ]
    return cargo, robots
