"""Astrobee cargo transport: N free-flyers carry one cargo of unknown inertia together.

## Description

`n_robots` Astrobees (1 to 8) hold one cargo transfer bag by its handrails inside an ISS module
(microgravity) and carry it along a reference trajectory of the cargo (`agents.trajectories`:
a figure-eight with a yaw ramp, optionally with roll and pitch oscillations, or a hover). Every
robot runs its own constrained UKF (`estimator.cargo_estimator.CargoEstimator`) that estimates the
cargo's ten inertial parameters from its own IMU, arm encoders, localization fixes and propulsion
command, and from the grasp wrenches the other robots send over a communication channel with
latency, loss and noise (`envs.comms.CommChannel`). Each robot's estimate (mean and standard
deviation) is part of its observation, so controllers can use it.

One control step (62.5 Hz, Astrobee's GNC rate; sources §3.1, docs/design.md), in this order:
actions are validated, clipped and scaled; MuJoCo advances `frame_skip` physics steps; every
robot's sensors are read with the seeded noise model (`envs.sensors`); each estimator ingests
its own packet and its own command and publishes its wrench; the channel delivers what is due;
the estimators update; observations, rewards, terminations, truncations and infos are assembled.
Ground truth (true cargo parameters, estimate errors) goes to `infos` and `state()` only.

The physics and estimation live in the plain class `CargoTransport` (`envs.transport`, no
PettingZoo); `AstrobeeCargoEnv` is the thin `pettingzoo.ParallelEnv` on top (agents `astrobee_0`
...). Both take one validated configuration, `EnvConfig` (`envs.config`), whose fields are the
Arguments below; the navigation filter is `envs.navigation`, the faults `envs.faults`, the
observation layout `envs.observations`. Beside the dict API, `step_arrays(actions)` takes the
actions as one (n_robots, 8) array and returns the same step as arrays in robot index order
(`ArrayStep`), without building dicts; the SB3 adapter (`envs.wrappers`) steps through it.

## Action Space

`Box(-1, 1, (8,), float32)` per agent. Values outside [-1, 1] are clipped (counted in
`infos["clipped_actions"]`). Thrust is a body-frame wrench at the robot's `thrust` site; the
actuation noise of the noise profile is added after clipping (`SensorSuite.actuate`). `step`
needs an action for every agent in `agents`; an action for an agent that is no longer live (a
robot that let go of the cargo, section Release) is ignored, as PettingZoo's `aec_to_parallel`
does; an unknown agent name raises `ValueError`.

| Index | Action (after scaling)                   | Min | Max | Unit | MJCF actuator         |
|-------|------------------------------------------|-----|-----|------|-----------------------|
| 0     | force along base x, a * 0.41             | -1  | 1   | N    | `astrobee_i/force_x`  |
| 1     | force along base y, a * 0.23             | -1  | 1   | N    | `astrobee_i/force_y`  |
| 2     | force along base z, a * 0.38             | -1  | 1   | N    | `astrobee_i/force_z`  |
| 3     | torque about base x, a * 0.045           | -1  | 1   | N m  | `astrobee_i/torque_x` |
| 4     | torque about base y, a * 0.022           | -1  | 1   | N m  | `astrobee_i/torque_y` |
| 5     | torque about base z, a * 0.033           | -1  | 1   | N m  | `astrobee_i/torque_z` |
| 6     | tilt target: -pi/2 + a * 0.5             | -1  | 1   | rad  | `astrobee_i/tilt`     |
| 7     | pan target: 0 + a * 0.5                  | -1  | 1   | rad  | `astrobee_i/pan`      |

The thrust limits are the actuators' `ctrlrange` (`World.robot_model(i).thrust_limit`). The arm
targets are offsets from the deployed pose (tilt -pi/2, pan 0); the target sent to the servo moves
towards the requested one at most 0.12 rad/s (URDF joint velocity limit, sources §5, docs/design.md)
and stays within the joint ranges.

## Observation Space

`Box(float64)` per agent, local to the robot and built only from its own noisy sensors, its own
commands, its known model, the reference and the messages it received; never from the truth.
"Base frame" below is the robot's own estimate of its base attitude. With P = n_robots - 1 peer
slots (peers in increasing index, skipping the robot itself) and E = 20 if `observe_estimates`
else 0, the size is 35 + 12 P + E (n_robots=2: 47 without, 67 with estimates).

| Index          | Observation                                                  | Unit       |
|----------------|--------------------------------------------------------------|------------|
| 0-2            | base position minus its reference position, base frame      | m          |
| 3-5            | base velocity minus its reference velocity, base frame      | m/s        |
| 6-8            | base attitude error: rotation vector of R_ref^T R_base       | rad        |
| 9-11           | base angular velocity, base frame (gyro, period mean)       | rad/s      |
| 12-13          | arm joint angles tilt, pan (encoders)                       | rad        |
| 14-15          | arm joint targets tilt, pan (what the servos are sent)      | rad        |
| 16-18          | cargo reference position minus base position, base frame    | m          |
| 19-21          | cargo reference velocity, base frame                        | m/s        |
| 22-24          | cargo reference acceleration, base frame                    | m/s^2      |
| 25-27          | cargo reference angular velocity, base frame                | rad/s      |
| 28-30          | cargo reference angular acceleration, base frame            | rad/s^2    |
| 31-32          | reference pan angle and pan rate (the arm pan ramp)         | rad, rad/s |
| 33-34          | arm joint rates tilt, pan: the servo targets' rate this step | rad/s     |
| 35+12p+(0-5)   | peer p's last wrench on the cargo, this robot's base axes   | N, N m     |
| 35+12p+6       | age of that message (0 before the first)                    | s          |
| 35+12p+7       | valid: 1 once a message of peer p has arrived, else 0       | -          |
|                | (0 again, with the whole slot, once peer p has let go)      |            |
| 35+12p+(8-9)   | peer p's arm angles tilt, pan (encoders) when it sent it    | rad        |
| 35+12p+(10-11) | peer p's arm joint rates (servo targets) when it sent it    | rad/s      |
| 35+12P+(0-9)   | estimate mean pi, this robot's grasp frame (if observed)    | see below  |
| 45+12P+(0-9)   | standard deviations of those ten parameters (if observed)   | see below  |

A peer's wrench is [force; moment about the peer's grasp point] (zeros before its first message).
pi = [m, m c_x, m c_y, m c_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m, kg m^2; inertia about
the grasp point, `estimator.inertia` conventions).

`observation_layout(n_robots, observe_estimates)` returns these slices by name.

Base state: each robot dead-reckons with its own gyro and accelerometer between localization
fixes and blends the fixes in with a Kalman gain (`BaseNavigator`). Base reference: the pose the
base would have if the cargo were exactly on its reference, with the grasp rigid at the robot's
current (measured) arm angles: R_ref = R_cargo,ref R_cargo<-handrail R_base<-grasp(q)^T and the
matching position; its velocity is the cargo reference's rigid-body velocity at that point (the
arm's own motion is left out). The handrail each robot holds is known geometry (the cargo's
handrail sites); only the cargo's inertial parameters are unknown. A peer's wrench is the message's
world-axes wrench (sender's attitude estimate) rotated into this robot's base axes with its own.

## Rewards

Per agent: `reward = shared_reward * team + (1 - shared_reward) * individual`, term by term:

- `track` = w_track * (-|p_cargo - p_ref| - 0.5 * angle(R_ref^T R_cargo)) (true cargo frame pose,
  m and rad; the same for team and individual);
- `effort` = w_effort * (-sum(a^2)) of the clipped action (team: mean over robots);
- `info` = w_info * (decrease of sum(log std) of the robot's ten-parameter estimate this step)
  (team: mean over robots; 0 when the estimators are off);
- `contact` = w_contact * (-number of contacts with the module's walls and handrails): team, all
  contacts of any robot or the cargo; individual, those of this robot plus those of the cargo.

Every term enters `infos[agent]["reward_<term>"]` already mixed and weighted; they sum to the
reward.

## Starting State

At each `reset` the cargo's inertial parameters are drawn (or set) from the arguments; the
robots hold the cargo with their arms deployed, everything at rest, the cargo frame at the module
centre, aligned with the module. The first observation comes from one sensor reading at rest
(a localization fix, encoders, IMU at rest plus noise), which the estimators also ingest.

## Episode End

Termination (every agent): any contact of a robot or the cargo with the module
(`infos["termination_reason"] == "wall_contact"`), or a non-finite or unstable physics state or a
non-finite observation (`"non_finite"`; the observation is then returned with zeros in place of
the non-finite entries, so no NaN ever leaves the env without a reason). Termination (one agent):
its robot lets go of the cargo (`"released"`, section Release); the others go on, and the
episode ends when the last one has let go. Truncation (every live agent): after `max_cycles`
control steps. The dicts `step` returns hold the agents that were live at the step; an agent
leaves `agents` at the step that terminates or truncates it. `agents` is empty once the episode
has ended; stepping again raises `RuntimeError` until `reset`.

## Infos

Per agent: `reward_<term>` (above), `termination_reason` (None, "wall_contact", "non_finite",
"released"), `releases` (robots that have let go of the cargo so far this episode), `holding`
(the indices of the robots holding it after this step), `released_momentum` (only at the step
its robot lets go: the linear momentum, kg m/s, and the angular momentum about the module
origin, kg m^2/s, world axes, that it carries away), `time_s`, `clipped_actions` (entries of
this agent's action outside [-1, 1] this step), `saturated` (the share of the requested thrust
this step that was not delivered: 1 - |a_c| / |a| over the six thrust entries of the action a as
given and a_c as clipped to [-1, 1]; 0 when none exceeds its limit; in [0, 1]),
`wall_contacts`, `true_params` (the cargo's pi in this robot's grasp frame), with estimators on:
`estimate`, `estimate_std`, `mass_rel_err`, `com_err_m`, `principal_rel_err` (list of 3, sorted
principal moments), `estimator` (the estimator's counters, `CargoEstimator.counters`: updates,
rolled_back, skipped_missing, skipped_bad_reading, skipped_peer_tainted, skipped_after_gate,
skipped_low_excitation, gated, mode_fallbacks (reports that fell back to the eigenvalue-clipped
body), bad_readings, missing_imu, fixes, stale_messages, pending); `comm`
(channel statistics); and `faults`: what was injected on this robot so far this episode
(imu_frames_missing, fixes_missing, propulsion_steps, messages_lost_sent,
messages_lost_received, messages_delayed_sent, messages_delayed_received: message copies) and
`active`, the kinds of its faults active at this step.

## Faults

`faults` is a list of faults, each a dict (or a `Fault`) with `kind`, `robot`, `start_s`,
`duration_s` and its kind's own fields; a fault is active at the control steps whose end time
k * dt lies in [start_s, start_s + duration_s). Faults draw from their own generator (spawned
from the reset seed only when there are faults) and act after the ordinary noise draws, so a run
with faults and one without, seeded alike, are identical until the first fault starts.

| kind                  | fields           | effect                                            |
|-----------------------|------------------|---------------------------------------------------|
| `imu_dropout`         | `prob` (1.0)     | its IMU frames are missing (each with `prob`)     |
| `localization_outage` |                  | it gets no localization fix                       |
| `propulsion`          | `scale` (0.0)    | delivered thrust = `scale` x (command + noise);   |
|                       |                  | it and its estimator still believe the command    |
| `comm_burst`          | `prob` (1.0)     | message copies sent by or to it are lost          |
| `comm_delay`          | `delay_s` (> 0)  | its messages arrive `delay_s` later than the      |
|                       |                  | latency (rounded to control periods)              |

What the estimators do, and what it costs them (two robots, nominal noise, figure-eight, the
scripted controller's actions replayed; the 18 s figures are asserted in
tests/test_robustness.py, the 60 s ones were measured once the same way; "changed": final error
minus that of the same run without the fault):

- a missing IMU frame is held (the navigator and the estimator use the previous one), counted
  (`missing_imu`), and taints the instants within the estimator's filter memory (about 4.9 s):
  they are skipped (`skipped_bad_reading`) and the messages of those instants go out flagged, so
  the peers skip them too (`skipped_peer_tainted`). The estimate does not move meanwhile;
- during an outage the robot dead-reckons (navigation drift < 2 cm over 5 s); its estimator counts
  fewer `fixes` and pauses the relative-grasp average; the wrench balance itself needs no fix;
- a lost message costs the receiver that instant (`skipped_missing`, one per lost copy); a
  delayed one within the estimators' `history_s` (2 s) costs nothing, a later one costs the
  instant and is counted as `stale_messages` on arrival;
- for these four, the final errors exceed the fault-free run's by less than 1 % mass and 5 mm
  centre of mass (faults of 1-5 s at 9 s, 18 s runs);
- a weakened or dead thruster makes the wrench balance inconsistent. Once the estimate is
  confident, the NIS gate rejects the first inconsistent instant (`gated`), the updates of the
  instants within the filter memory before it are undone (`rolled_back`) and those after it
  skipped (`skipped_after_gate`): half or no thrust for 3 s at 30 s changed the final (60 s)
  errors by less than 0.3 % mass and 0.5 mm; no thrust for 3 s at 9 s by less than 0.5 % and
  3 mm at 18 s; half thrust for 3 s at 9 s is caught by the gate too (every robot's filter gates
  at least one instant and ends within 2 % mass and 1 cm of the fault-free run,
  `tests/test_robustness.py`). A fault the gate cannot see is absorbed as a wrong cargo: 80 %
  thrust for 10 s at 30 s gave 2.7-3.8 % and 1.5-2.6 cm at 60 s (measured with the scripted
  controller, nominal noise, seed 0, before the estimators' motion-noise model; not re-measured).

## Release

`release_at` lists (robot, time_s) pairs: robot `robot` lets go of the cargo at the first
control instant k * dt >= time_s (k >= 1). Step k is its last: it acts in it, and `step` returns
its final observation with `terminations[agent] = True` and `termination_reason` "released";
the agent then leaves `agents`. At the end of step k (after its physics, sensors and estimator
updates; before the observations):

- the world is rebuilt without the robot (`World.without_robots`): the cargo and the robots
  still holding it continue from exactly the same positions and velocities (`World.load_state`),
  so their momentum is unchanged; the robot and the momentum it carries (`released_momentum`)
  leave the simulation. It is removed, not kept as a free body: no one commands it any more, it
  would drift through the module into walls (ending the episode) or into the cargo, and as long
  as it touches nothing, removing it changes nothing for the others;
- it leaves the channel (`CommChannel.disconnect`): its messages in flight are discarded and no
  further copies are addressed to it; every other robot's peer slot for it is zeroed;
- every remaining estimator is told its new peers (`CargoEstimator.set_peers`): the instants
  waiting for the robot's messages are given up (counted once, `skipped_missing`), and the
  instants within the filters' memory of the change (about 4.9 s) are skipped as tainted
  (`skipped_bad_reading`): they mix the balance of two different subsystems. Then the updates
  resume with the remaining robots' messages only, and no counter grows because of the robot.

A release due at a step whose physics is not finite does not happen (the episode ends with
"non_finite"). Measured (tests/test_robustness.py): the last of two or three robots letting go
at 8 s, ideal sensors, the others' mass errors stay below 1 % and their centre-of-mass errors
below 5 mm at 20 s; the total momentum is conserved across the rebuild to 1e-12. With nominal
noise (three robots, robot 2 letting go at 8 s, measured once) the other two ended at 40 s within
1.3 % mass and 1.4 cm, as the same run without the release did (1.3 %, 2.1 cm).

## State

`state()` is the full true state, float64, of a fixed size whoever still holds the cargo: time;
qpos; qvel; for every body but the world (cargo, then each robot's bodies) its frame's position,
quaternion (w, x, y, z), linear and angular velocity (world axes); the true cargo pi in the cargo
frame (10); the reference (position, velocity, acceleration, quaternion, angular velocity,
angular acceleration, pan, pan rate: 21); the arm targets (2 per robot); one flag per robot, 1
while it holds the cargo, 0 once it has let go. A robot that has let go is no longer simulated:
its qpos, qvel, body and arm-target entries are zeros (its quaternions too: never a valid one).

## Arguments

| Argument            | Default       | Meaning                                                  |
|---------------------|---------------|----------------------------------------------------------|
| `n_robots`          | 2             | robots holding the cargo, 1 to 8: up to 4 on the half    |
|                     |               | CTB, 5 to 8 on the single CTB (eight handrails; `World`) |
| `trajectory`        | "figure8_yaw" | cargo reference: one of `Trajectory.NAMES`, "excite"     |
|                     |               | (the team's designed excitation, `agents.excitation`:    |
|                     |               | shipped, else designed and cached) or a design JSON path |
| `fast`              | False         | twice the figure-eight speed                             |
| `noise`             | "nominal"     | sensor and actuation noise: one of `NOISE_PROFILES`      |
| `cargo_mass_kg`     | 5.0           | mass in [0.1, 100] kg, or (low, high): uniform draw at   |
|                     |               | each reset                                               |
| `cargo_com_m`       | None          | CoM in the cargo frame (3, within the bag's half sizes), |
|                     |               | or None: uniform in +-0.03 m                             |
| `cargo_inertia`     | None          | (I_xx, I_yy, I_zz, I_xy, I_xz, I_yz) about the CoM,      |
|                     |               | physical, principal moments <= m d^2 (d: bag diagonal); |
|                     |               | or None: uniform box of the bag's size and that mass     |
|                     |               | (half CTB 0.42 x 0.30 x 0.25 m, single CTB 0.502 x 0.425 |
|                     |               | x 0.248 m: `World.cargo_size_m`)                         |
| `comm_latency`      | 0.0           | message latency in [0, 60] s (rounded to periods)        |
| `comm_drop`         | 0.0           | probability that one message to one receiver is lost     |
| `comm_noise`        | (0.0, 0.0)    | std of the noise on sent wrenches (force N, moment N m), |
|                     |               | at most (10, 1)                                          |
| `control_hz`        | 62.5          | control rate, 10 to 1000 Hz                              |
| `frame_skip`        | None          | physics steps per control step (None: MJCF's 16 ms step) |
| `max_cycles`        | None          | control steps per episode (None: 90 s, 5625 at 62.5 Hz)  |
| `w_track`           | 1.0           | weight of the tracking term (every weight: |w| <= 1e6)   |
| `w_effort`          | 0.01          | weight of the effort term                                |
| `w_info`            | 0.0           | weight of the information-gain term                      |
| `w_contact`         | 1.0           | weight of the wall-contact term                          |
| `shared_reward`     | 1.0           | weight of the team reward against the individual one     |
| `observe_estimates` | True          | append the estimate mean and std to the observation     |
| `estimators`        | True          | run the estimators (False: physics only, benchmarks)     |
| `estimator_kwargs`  | None          | keyword arguments of `CargoEstimator`; `actuation_noise` |
|                     |               | defaults to the noise profile's                          |
| `faults`            | None          | injected faults (section Faults), a list of dicts        |
| `release_at`        | None          | (robot, time_s) pairs: robot lets go of the cargo then   |
|                     |               | (section Release), each robot at most once               |
| `render_mode`       | None          | None, "rgb_array" or "human"                             |
| `render_width`      | 640           | rgb_array width, pixels (at most 1280)                   |
| `render_height`     | 480           | rgb_array height, pixels (at most 720)                   |
| `render_camera`     | "track"       | "track" (free camera on the cargo) or an MJCF camera     |

## Version History

- v0: first version. Later additions, compatible: `faults`; argument bounds (cargo mass 0.1-100
  kg, centre of mass within the bag, inertia at most m d^2, control rate 10-1000 Hz, latency at
  most 60 s, channel noise at most (10 N, 1 N m), reward weights at most 1e6 in size);
  `release_at`, with the holding flags appended to `state()` (n_robots more entries); the
  arguments as one validated `EnvConfig` (`AstrobeeCargoEnv(config)` or the keyword arguments
  above); the env deep-copies and pickles (a live renderer is not copied); `render_mode="human"`
  without a display raises `RuntimeError`; importing `astrocargo.envs` registers the Gymnasium
  form `astrocargo/AstrobeeCargo-v0`; `trajectory="excite"` (the team's designed excitation)
  or the path of a design JSON file; `infos["saturated"]`; `step_arrays`. Changed: the
  observation carries the robot's arm joint rates (33-34) and each peer slot the sender's arm
  angles and rates (its last four entries): 35 + 12 P + E entries instead of 33 + 8 P + E.
  Changed: each estimator models the noise its motion brings into the balance, conditioned on
  the team's IMUs (`motion_fusion="team"`), and the IMU's period means enter its pre-filter
  with a zero-order hold (no dt/2 lag behind the encoders): estimates differ from earlier
  versions.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

# Re-exported: the names scripts, agents and tests import from this module.
from astrocargo.envs.config import (  # noqa: F401
    CARGO_MASS_LIMITS_KG,
    CONTROL_HZ,
    CONTROL_HZ_LIMITS,
    EPISODE_S,
    MAX_COMM_LATENCY_S,
    MAX_COMM_NOISE,
    MAX_REWARD_WEIGHT,
    RENDER_CAMERA_TRACK,
    RENDER_MODES,
    REWARD_TERMS,
    EnvConfig,
)
from astrocargo.envs.faults import FAULT_COUNTERS, FAULT_KINDS, Fault  # noqa: F401
from astrocargo.envs.navigation import NAV_STD_FLOOR, BaseNavigator  # noqa: F401
from astrocargo.envs.observations import observation_bounds, observation_layout  # noqa: F401
from astrocargo.envs.transport import (  # noqa: F401
    ACTION_DIM,
    ARM_OFFSET_RAD,
    ARM_SPEED_RADPS,
    CARGO_COM_SPREAD_M,
    LOG_STD_FLOOR,
    REWARD_KEYS,
    ROTATION_WEIGHT_M_PER_RAD,
    TERMINATION_REASONS,
    CargoTransport,
    StepResult,
)
from astrocargo.estimator.checks import all_finite

# Tracking camera: looking down the aisle (+x) from 1.5 m behind the cargo and 0.55 m above it,
# inside the module's 2.2 m square section (tests/test_env.py checks), framing cargo and robots.
TRACK_DISTANCE_M, TRACK_AZIMUTH_DEG, TRACK_ELEVATION_DEG = 1.6, 0.0, -20.0
VISIBLE_GEOM_GROUPS = (0, 1, 2, 3)  # visual and collision geoms; sites (4) off

# --------------------------------------------------------------------------- PettingZoo


def _require_display() -> None:
    """Raise ``RuntimeError`` when human rendering cannot open a window: on Linux without
    ``DISPLAY`` or ``WAYLAND_DISPLAY``, GLFW (MuJoCo's viewer) ends the whole process instead of
    raising, which would also take down test runners and env checkers."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise RuntimeError(
            'render_mode="human" needs a display (neither DISPLAY nor WAYLAND_DISPLAY is set); '
            'without one use render_mode="rgb_array" (with MUJOCO_GL=egl or osmesa) or None'
        )


@dataclass(slots=True)
class ArrayStep:
    """``AstrobeeCargoEnv.step_arrays``' result: what ``step`` returns as dicts over the live
    agents, as arrays and a list in robot index order (``CargoTransport.step`` builds them)."""

    observations: np.ndarray  # (n_robots, obs_dim) float64
    rewards: np.ndarray  # (n_robots,) float64
    terminated: np.ndarray  # (n_robots,) bool
    truncated: np.ndarray  # (n_robots,) bool
    infos: list[dict[str, Any] | None]


class AstrobeeCargoEnv(ParallelEnv):
    """PettingZoo ParallelEnv of ``CargoTransport``; see the module docstring."""

    metadata = {
        "name": "astrobee_cargo_v0",
        "render_modes": list(RENDER_MODES),
        "render_fps": round(CONTROL_HZ),  # round(1 / control period): 62 at 62.5 Hz
        "is_parallelizable": True,
    }

    def __init__(self, config: EnvConfig | None = None, **kwargs: Any) -> None:
        """Keyword arguments: the fields of ``EnvConfig`` (the module docstring's Arguments
        table); or one ready ``EnvConfig``."""
        if config is None:
            config = EnvConfig(**kwargs)
        elif kwargs:
            raise ValueError("give either an EnvConfig or keyword arguments, not both")
        if config.render_mode == "human":
            _require_display()
        self.config = config
        self.sim = CargoTransport(config)
        self.max_cycles = config.max_cycles or round(EPISODE_S * self.sim.control_hz)
        cameras = [self.sim.model.camera(c).name for c in range(self.sim.model.ncam)]
        if config.render_camera != RENDER_CAMERA_TRACK and config.render_camera not in cameras:
            raise ValueError(
                f"unknown render_camera {config.render_camera!r}; allowed: "
                f"{[RENDER_CAMERA_TRACK, *cameras]}"
            )
        self.render_mode = config.render_mode
        self.render_size = (config.render_height, config.render_width)
        self.render_camera = config.render_camera
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.sim.dt_s)}
        self.possible_agents = [f"astrobee_{i}" for i in range(self.sim.n_robots)]
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self._all_live = np.ones(self.sim.n_robots, dtype=bool)
        self._all_live.flags.writeable = False
        self.state_space = spaces.Box(-np.inf, np.inf, (self.sim.state_dim,), np.float64)
        low, high = observation_bounds(self.sim.obs_layout)
        self.observation_spaces = {
            a: spaces.Box(low, high, dtype=np.float64) for a in self.possible_agents
        }
        self.action_spaces = {
            a: spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32) for a in self.possible_agents
        }
        self._root_rng: np.random.Generator | None = None
        self._renderer: mujoco.Renderer | None = None
        self._renderer_model: mujoco.MjModel | None = None
        self._viewer: Any = None
        self._viewer_model: mujoco.MjModel | None = None
        self._episode_over = True

    # PettingZoo requires the same object at every call: the spaces are built once. Agents have
    # identical spaces but each its own object, so seeding one agent's space seeds no other.
    def observation_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self.action_spaces[agent]

    def _check_agent(self, agent: str) -> None:
        if agent not in self._index:
            raise ValueError(f"unknown agent {agent!r}; agents: {self.possible_agents}")

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode. ``seed`` seeds one generator from which the sensor, channel and
        cargo generators are spawned; without it the previous generator continues."""
        del options
        if seed is not None or self._root_rng is None:
            self._root_rng = np.random.default_rng(seed)
        obs, infos = self.sim.reset(self._root_rng)
        self.agents = self.possible_agents[:]
        self._episode_over = False
        if self.render_mode == "human":
            self.render()
        return self._by_agent(obs), self._by_agent(infos)

    def step(
        self, actions: dict[str, np.ndarray]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        self._check_running()
        live = self.agents  # replaced by _advance, never changed in place
        result, truncated = self._advance(self._action_array(actions))
        if len(live) == len(self.possible_agents):  # live is possible_agents, in index order
            # One entry per robot in each: zip's strict check would cost more than the dicts.
            obs = dict(zip(live, result.observations))  # noqa: B905
            rewards = dict(zip(live, result.rewards.tolist()))  # noqa: B905
            infos = dict(zip(live, result.infos))  # noqa: B905
        else:
            rewards, obs, infos = self._by_live(
                live, (result.rewards.tolist(), result.observations, result.infos)
            )
        if result.released:
            released = {self.possible_agents[i] for i in result.released}
            terminations = {a: result.terminated or a in released for a in live}
        else:
            terminations = dict.fromkeys(live, result.terminated)
        truncations = dict.fromkeys(live, truncated)
        return obs, rewards, terminations, truncations, infos

    def step_arrays(self, actions: np.ndarray) -> ArrayStep:
        """``step`` with arrays in robot index order, no dicts: ``actions`` (n_robots, 8), the
        rows of agents no longer live ignored (``ValueError`` as ``step``'s). What it returns is
        ``ArrayStep``; the rows of robots that were not live at this step's start are zeros,
        False and None."""
        self._check_running()
        live_mask = self._live_mask()
        result, truncated = self._advance(self.sim.checked_actions(actions))
        terminated = live_mask & result.terminated
        if result.released:
            terminated[list(result.released)] = True
        return ArrayStep(
            result.observations, result.rewards, terminated, live_mask & truncated, result.infos
        )

    def _check_running(self) -> None:
        if self._episode_over:
            raise RuntimeError(
                "the episode has ended (or reset() was never called): call reset() before step()"
            )

    def _live_mask(self) -> np.ndarray:
        """Whether each robot (index order) is a live agent, bool (n_robots,)."""
        if len(self.agents) == len(self.possible_agents):
            return self._all_live  # read-only: the callers combine it into new arrays
        mask = np.zeros(len(self.possible_agents), dtype=bool)
        mask[[self._index[a] for a in self.agents]] = True
        return mask

    def _advance(self, actions: np.ndarray) -> tuple[StepResult, bool]:
        """One control step of the checked ``actions`` (n_robots, 8): the core's result and
        whether the episode is truncated (``max_cycles``); the agents that are done leave."""
        result = self.sim.step_checked(actions)
        truncated = self.sim.step_count >= self.max_cycles
        if result.terminated or truncated or result.released:
            done = {self.possible_agents[i] for i in result.released}
            if result.terminated or truncated:
                done = set(self.agents)
            self.agents = [a for a in self.agents if a not in done]
            if not self.agents:
                self._episode_over = True
        if self.render_mode == "human":
            self.render()
        return result, truncated

    def _by_live(self, live: list[str], columns: tuple) -> list[dict[str, Any]]:
        """Each of ``columns`` (indexed by robot) as a dict over the ``live`` agents (some of the
        robots: ``step`` zips the columns of all of them itself)."""
        rows = [self._index[a] for a in live]
        return [{a: values[i] for a, i in zip(live, rows, strict=True)} for values in columns]

    def _action_array(self, actions: dict[str, np.ndarray]) -> np.ndarray:
        """Every live agent's validated action in one array (rows of robots that have let go:
        zeros); actions given for agents no longer live are ignored, as PettingZoo's
        ``aec_to_parallel`` does."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict agent -> array, got {type(actions).__name__}")
        agents = self.agents
        # Every live agent's action at once; anything off (an unknown agent, missing, ragged,
        # not finite) takes the checks below, which say what is wrong.
        stacked = None
        if len(actions) == len(agents):
            try:
                stacked = np.array([actions[a] for a in agents], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                stacked = None
        if (
            stacked is not None
            and stacked.shape == (len(agents), ACTION_DIM)
            and all_finite(stacked)
        ):
            if len(agents) == self.sim.n_robots:
                return stacked
            out = np.zeros((self.sim.n_robots, ACTION_DIM))
            out[self._live_rows()] = stacked
            return out
        return self._checked_action_array(actions)

    def _checked_action_array(self, actions: dict[str, np.ndarray]) -> np.ndarray:
        """``_action_array`` agent by agent: ``ValueError`` says which action is wrong."""
        for agent in actions:
            if agent not in self._index:
                raise ValueError(f"action for unknown agent {agent!r}; agents: {self.agents}")
        out = np.zeros((self.sim.n_robots, ACTION_DIM))
        for agent in self.agents:
            i = self._index[agent]
            if agent not in actions:
                raise ValueError(f"no action for agent {agent!r}")
            try:
                a = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(f"action of agent {agent!r} is not numeric: {err}") from err
            if a.shape != (ACTION_DIM,):
                raise ValueError(
                    f"action of agent {agent!r} must have shape ({ACTION_DIM},), got {a.shape}"
                )
            if not np.isfinite(a).all():
                raise ValueError(f"action of agent {agent!r} is not finite: {a}")
            out[i] = a
        return out

    def _live_rows(self) -> list[int] | slice:
        """The rows of the live agents: a slice while every agent is live."""
        if len(self.agents) == len(self.possible_agents):
            return slice(None)
        return [self._index[a] for a in self.agents]

    def _by_agent(self, values: Any, agents: list[str] | None = None) -> dict[str, Any]:
        """``values`` (indexed by robot) for ``agents`` (default: every possible agent)."""
        agents = self.possible_agents if agents is None else agents
        return {agent: values[self._index[agent]] for agent in agents}

    def state(self) -> np.ndarray:
        return self.sim.state()

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        if self.render_mode == "rgb_array":
            return self._render_rgb()
        if self._viewer is not None and self._viewer_model is not self.sim.model:
            self._viewer.close()  # a robot let go: the world was rebuilt without it
            self._viewer = None
        if self._viewer is None:
            _require_display()  # GLFW would end the process without one
            import mujoco.viewer  # only for human rendering: needs a display

            self._viewer = mujoco.viewer.launch_passive(self.sim.model, self.sim.data)
            self._viewer_model = self.sim.model
        self._viewer.sync()
        return None

    def _render_rgb(self) -> np.ndarray:
        height, width = self.render_size
        if self._renderer is not None and self._renderer_model is not self.sim.model:
            self._renderer.close()  # a robot let go: the world was rebuilt without it
            self._renderer = None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.sim.model, height=height, width=width)
            self._renderer_model = self.sim.model
            self._scene_option = mujoco.MjvOption()
            self._scene_option.geomgroup[:] = 0
            for group in VISIBLE_GEOM_GROUPS:
                self._scene_option.geomgroup[group] = 1
        camera: str | mujoco.MjvCamera = self.render_camera
        if camera == RENDER_CAMERA_TRACK:
            camera = mujoco.MjvCamera()
            camera.type = mujoco.mjtCamera.mjCAMERA_FREE
            camera.lookat[:] = self.sim.data.xpos[self.sim.world.cargo_body]
            camera.distance = TRACK_DISTANCE_M
            camera.azimuth = TRACK_AZIMUTH_DEG
            camera.elevation = TRACK_ELEVATION_DEG
        self._renderer.update_scene(self.sim.data, camera=camera, scene_option=self._scene_option)
        return self._renderer.render()

    # A copy (copy.deepcopy, pickle) continues the episode bit for bit; a live renderer or viewer
    # is not copied (it holds a GL context or a window): the copy opens its own when it renders.
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update(_renderer=None, _renderer_model=None, _viewer=None, _viewer_model=None)
        return state

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
