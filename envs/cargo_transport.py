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

One control step (62.5 Hz, Astrobee's GNC rate; facts file section 3.1), in this order:
actions are validated, clipped and scaled; MuJoCo advances `frame_skip` physics steps; every
robot's sensors are read with the seeded noise model (`envs.sensors`); each estimator ingests
its own packet and its own command and publishes its wrench; the channel delivers what is due;
the estimators update; observations, rewards, terminations, truncations and infos are assembled.
Ground truth (true cargo parameters, estimate errors) goes to `infos` and `state()` only.

The physics and estimation live in the plain class `CargoTransport` (no PettingZoo);
`AstrobeeCargoEnv` is the thin `pettingzoo.ParallelEnv` on top (agents `astrobee_0` ...).

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
towards the requested one at most 0.12 rad/s (URDF joint velocity limit, facts file section 5)
and stays within the joint ranges.

## Observation Space

`Box(float64)` per agent, local to the robot and built only from its own noisy sensors, its own
commands, its known model, the reference and the messages it received; never from the truth.
"Base frame" below is the robot's own estimate of its base attitude. With P = n_robots - 1 peer
slots (peers in increasing index, skipping the robot itself) and E = 20 if `observe_estimates`
else 0, the size is 33 + 8 P + E (n_robots=2: 41 without, 61 with estimates).

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
| 33+8p+(0-5)    | peer p's last wrench on the cargo, this robot's base axes   | N, N m     |
| 33+8p+6        | age of that message (0 before the first)                    | s          |
| 33+8p+7        | valid: 1 once a message of peer p has arrived, else 0       | -          |
|                | (0 again, with the whole slot, once peer p has let go)      |            |
| 33+8P+(0-9)    | estimate mean pi, this robot's grasp frame (if observed)    | see below  |
| 43+8P+(0-9)    | standard deviations of those ten parameters (if observed)   | see below  |

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
this agent's action outside [-1, 1] this step),
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
  3 mm at 18 s. A fault the gate cannot see is absorbed as a wrong cargo: half thrust for 3 s at
  9 s (estimate still wide) gave the robot's own estimator 6.7 % extra mass error and 5 cm at
  18 s, 0.6 % and 9 mm at 60 s; 80 % thrust for 10 s at 30 s, 2.7-3.8 % and 1.5-2.6 cm at 60 s
  (measured with the scripted controller, nominal noise, seed 0).

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
| `trajectory`        | "figure8_yaw" | cargo reference: one of `Trajectory.NAMES`               |
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
  `release_at`, with the holding flags appended to `state()` (n_robots more entries).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from astrocargo.agents.trajectories import Reference, ReferenceValues, Trajectory
from astrocargo.envs.comms import FAULT_STATS, CommChannel
from astrocargo.envs.sensors import (
    NOISE_PROFILES,
    NoiseProfile,
    SensorPacket,
    SensorSuite,
    estimator_noise_kwargs,
)
from astrocargo.envs.sensors import noise_profile as get_noise_profile
from astrocargo.envs.world import (
    ARM_DEPLOYED_RAD,
    MAX_ROBOTS,
    MAX_TIMESTEP_S,
    World,
    _mat_to_quat,
    _quat_to_mat,
)
from astrocargo.estimator.cargo_estimator import CargoEstimator, exp_so3_rows
from astrocargo.estimator.inertia import (
    check_physical,
    com_error_m,
    mass_rel_error,
    params_from_mass_com_inertia,
    principal_rel_errors,
    vec_to_inertia,
)
from astrocargo.estimator.rne import (
    RobotDescription,
    as_rows,
    grasp_pose_rows,
    m_m,
    m_mt,
    m_v,
    mt_m,
    mt_v,
    norm3,
    v_add,
    v_cross,
    v_scale,
    v_sub,
)

ACTION_DIM = 8
ARM_OFFSET_RAD = 0.5  # reach of the arm actions around the deployed pose
ARM_SPEED_RADPS = 0.12  # URDF joint velocity limit (facts file section 5)
CONTROL_HZ = 62.5  # Astrobee GNC and PMC rate (facts file section 3.1)
EPISODE_S = 90.0  # default episode length: the seed paper's runs last 90 s
CARGO_COM_SPREAD_M = 0.03  # sampled centre of mass: uniform in +-this per axis
# Accepted cargo masses: an empty bag (the ISAAC cargo model's 0.5 kg, facts file section 7) to
# ten Astrobees' worth; beyond that two robots' 0.4 N cannot move it within an episode.
CARGO_MASS_LIMITS_KG = (0.1, 100.0)
CONTROL_HZ_LIMITS = (10.0, 1000.0)  # estimator filters need >= 10 Hz (1 Hz pre-filter cutoff)
MAX_REWARD_WEIGHT = 1e6  # keeps every weighted term finite
MAX_COMM_LATENCY_S = 60.0  # far beyond the estimators' history (2 s): nothing then arrives in time
MAX_COMM_NOISE = (10.0, 1.0)  # force N, moment N m: 25 times the propulsion limits
ROTATION_WEIGHT_M_PER_RAD = 0.5  # tracking term: metres of position error per radian
RENDER_CAMERA_TRACK = "track"
# Tracking camera: looking down the aisle (+x) from 1.5 m behind the cargo and 0.55 m above it,
# inside the module's 2.2 m square section (tests/test_env.py checks), framing cargo and robots.
TRACK_DISTANCE_M, TRACK_AZIMUTH_DEG, TRACK_ELEVATION_DEG = 1.6, 0.0, -20.0
VISIBLE_GEOM_GROUPS = (0, 1, 2, 3)  # visual and collision geoms; sites (4) off
# Floors of the navigation filter's noise model, so the ideal profile stays well posed.
NAV_STD_FLOOR = 1e-9
LOG_STD_FLOOR = 1e-12
REWARD_TERMS = ("track", "effort", "info", "contact")
REWARD_KEYS = tuple(f"reward_{t}" for t in REWARD_TERMS)  # their names in infos
_BAD_QACC = int(mujoco.mjtWarning.mjWARN_BADQACC)
_EMPTY_PEER_SLOT = (0.0,) * 8  # a peer slot before its first message: wrench, age, valid
TERMINATION_REASONS = ("wall_contact", "non_finite", "released")  # "released": one agent


# --------------------------------------------------------------------------- small helpers


def _rotvec(rot: tuple) -> list[float]:
    """Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix given by its rows."""
    quat, vec = np.empty(4), np.empty(3)
    mujoco.mju_mat2Quat(quat, np.array(rot[0] + rot[1] + rot[2]))
    mujoco.mju_quat2Vel(vec, quat, 1.0)
    return vec.tolist()


def _arm_target(current: float, wanted: float, max_move: float, low: float, high: float) -> float:
    """The next servo target: ``wanted`` approached by at most ``max_move``, within the joint
    range [low, high] (np.clip's min-then-max, on floats)."""
    return min(max(current + min(max(wanted - current, -max_move), max_move), low), high)


def _mean(values: list[float], indices: tuple[int, ...]) -> float:
    """Mean of ``values`` at ``indices``, summed in order as numpy's mean of a few values."""
    total = -0.0
    for i in indices:
        total += values[i]
    return total / len(indices)


def observation_layout(n_robots: int, observe_estimates: bool = True) -> dict[str, slice]:
    """Index slices of each observation block (see the module docstring's table)."""
    sizes = [
        ("base_pos_err", 3),
        ("base_vel_err", 3),
        ("base_att_err", 3),
        ("base_ang_vel", 3),
        ("joint_pos", 2),
        ("joint_target", 2),
        ("ref_pos_rel", 3),
        ("ref_vel", 3),
        ("ref_acc", 3),
        ("ref_ang_vel", 3),
        ("ref_ang_acc", 3),
        ("ref_pan", 2),
    ]
    for p in range(n_robots - 1):
        sizes += [(f"peer{p}_wrench", 6), (f"peer{p}_age", 1), (f"peer{p}_valid", 1)]
    if observe_estimates:
        sizes += [("estimate_mean", 10), ("estimate_std", 10)]
    out, start = {}, 0
    for name, size in sizes:
        out[name] = slice(start, start + size)
        start += size
    out["all"] = slice(0, start)
    return out


# --------------------------------------------------------------------------- navigation


class BaseNavigator:
    """One robot's estimate of its own base pose and velocity, from its own sensors only.

    Between localization fixes it dead-reckons: attitude with the gyro's period-mean rate,
    velocity and position of the IMU point with the accelerometer's period-mean specific force
    (exact for ideal readings: that mean is the change of the IMU point's velocity over the
    period). At a fix it blends in the fixed attitude and position with Kalman gains built from
    the noise profile the robot knows (isotropic, so one 2x2 covariance serves all three axes).

    The state is kept on Python floats (3-vectors and the rows of 3x3 matrices as tuples, with
    rne's helpers): a few 3x3 products per step, which numpy's per-call overhead would dominate.
    """

    def __init__(self, robot: RobotDescription, dt_s: float, profile: NoiseProfile) -> None:
        self.imu_rot = robot.imu_rot
        self.imu_pos = robot.imu_pos
        self._imu_rot, self._imu_pos = as_rows(robot.imu_rot), tuple(robot.imu_pos.tolist())
        self.dt_s = float(dt_s)
        acc_var = max(profile.accel_std, NAV_STD_FLOOR) ** 2
        self.pos_var = max(profile.position_std_m, NAV_STD_FLOOR) ** 2
        self.att_var = max(profile.attitude_std_rad, NAV_STD_FLOOR) ** 2
        self.gyro_step_var = (max(profile.gyro_std, NAV_STD_FLOOR) * dt_s) ** 2
        dt = self.dt_s
        # Position-velocity model x' = F x + noise, F = [[1, dt], [0, 1]], noise covariance
        # acc_var [[dt^4 / 4, dt^3 / 2], [dt^3 / 2, dt^2]] (q00, q01, q11).
        self._q = (acc_var * (dt**4 / 4), acc_var * (dt**3 / 2), acc_var * dt**2)

    def reset(self, packet: SensorPacket) -> None:
        """Start at rest at the packet's localization fix."""
        if packet.base_pos_world is None or packet.base_quat_world is None:
            raise ValueError("the navigator starts from a packet with a localization fix")
        self._rot = as_rows(_quat_to_mat(packet.base_quat_world))
        if packet.gyro_imu is None or packet.accel_imu is None:
            self._last_imu = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # at rest
        else:
            self._last_imu = (packet.gyro_imu.tolist(), packet.accel_imu.tolist())
        self._w = m_v(self._imu_rot, self._last_imu[0])
        self._p = v_add(packet.base_pos_world.tolist(), m_v(self._rot, self._imu_pos))
        self._v = (0.0, 0.0, 0.0)
        self._cov = (self.pos_var, 0.0, 0.0, NAV_STD_FLOOR**2)  # c00, c01, c10, c11
        self.att_cov = self.att_var

    def update(self, packet: SensorPacket) -> None:
        """Propagate over one control period with the packet's IMU means (the previous ones when
        the frame is missing); blend in its fix."""
        dt = self.dt_s
        if packet.gyro_imu is not None and packet.accel_imu is not None:
            self._last_imu = (packet.gyro_imu.tolist(), packet.accel_imu.tolist())
        gyro, accel = self._last_imu
        w = m_v(self._imu_rot, gyro)
        rot_mid_imu = m_m(m_m(self._rot, exp_so3_rows(v_scale(0.5 * dt, w))), self._imu_rot)
        self._rot = m_m(self._rot, exp_so3_rows(v_scale(dt, w)))
        v_new = v_add(self._v, v_scale(dt, m_v(rot_mid_imu, accel)))
        self._p = v_add(self._p, v_scale(0.5 * dt, v_add(self._v, v_new)))
        self._v = v_new
        self._w = w
        # cov <- F cov F^T + Q
        c00, c01, c10, c11 = self._cov
        q00, q01, q11 = self._q
        a00, a01 = c00 + dt * c10, c01 + dt * c11  # first row of F cov
        self._cov = (a00 + a01 * dt + q00, a01 + q01, c10 + c11 * dt + q01, c11 + q11)
        self.att_cov += self.gyro_step_var
        if packet.base_pos_world is None or packet.base_quat_world is None:
            return
        fix_rot = as_rows(_quat_to_mat(packet.base_quat_world))
        gain_att = self.att_cov / (self.att_cov + self.att_var)
        error = _rotvec(mt_m(self._rot, fix_rot))
        self._rot = m_m(self._rot, exp_so3_rows(v_scale(gain_att, error)))
        self.att_cov *= 1.0 - gain_att
        fixed_imu = v_add(packet.base_pos_world.tolist(), m_v(self._rot, self._imu_pos))
        innovation = v_sub(fixed_imu, self._p)
        c00, c01, c10, c11 = self._cov
        gain_p, gain_v = c00 / (c00 + self.pos_var), c10 / (c00 + self.pos_var)
        self._p = v_add(self._p, v_scale(gain_p, innovation))
        self._v = v_add(self._v, v_scale(gain_v, innovation))
        self._cov = (c00 - gain_p * c00, c01 - gain_p * c01, c10 - gain_v * c00, c11 - gain_v * c01)

    def state_rows(self) -> tuple[tuple, tuple, tuple, tuple]:
        """Base attitude (rows), position, velocity and angular velocity (base frame), floats."""
        rot, w, imu = self._rot, self._w, self._imu_pos
        base_pos = v_sub(self._p, m_v(rot, imu))
        base_vel = v_sub(self._v, m_v(rot, v_cross(w, imu)))
        return rot, base_pos, base_vel, w

    @property
    def rot(self) -> np.ndarray:
        return np.array(self._rot)

    @property
    def w_base(self) -> np.ndarray:
        return np.array(self._w)

    @property
    def base_pos(self) -> np.ndarray:
        return np.array(self.state_rows()[1])

    @property
    def base_vel(self) -> np.ndarray:
        return np.array(self.state_rows()[2])


# --------------------------------------------------------------------------- physics + estimation


@dataclass(frozen=True)
class StepResult:
    """What one control step returns, per robot (index order); the rows of robots that let go
    of the cargo at an earlier step are zeros."""

    observations: np.ndarray  # (n_robots, obs_dim) float64
    rewards: np.ndarray  # (n_robots,)
    terminated: bool  # the episode ended for every robot (termination_reason)
    termination_reason: str | None
    infos: list[dict[str, Any] | None]  # None for a robot that let go at an earlier step
    released: tuple[int, ...] = ()  # the robots that let go of the cargo at this step


def _check_finite_number(name: str, value: Any, allowed: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    if not np.isfinite(value):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return float(value)


def _check_finite_array(name: str, value: Any, shape: tuple[int, ...], allowed: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (numbers only: no strings, no booleans)."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {allowed}, got {value!r}") from None
    if raw.dtype.kind not in "iuf" or raw.shape != shape or not np.all(np.isfinite(raw)):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return raw.astype(float)


def _check_choice(name: str, value: Any, allowed: Any) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; allowed: {sorted(allowed)}")
    return value


FAULT_KINDS: dict[str, tuple[str, ...]] = {  # kind -> its own optional fields
    "imu_dropout": ("prob",),
    "localization_outage": (),
    "propulsion": ("scale",),
    "comm_burst": ("prob",),
    "comm_delay": ("delay_s",),
}
# infos[agent]["faults"]: counted by the env, and by the channel (copies, comms.FAULT_STATS).
FAULT_COUNTERS = ("imu_frames_missing", "fixes_missing", "propulsion_steps")
_NO_FAULT_COUNTS = dict.fromkeys(FAULT_COUNTERS + tuple(f"messages_{k}" for k in FAULT_STATS), 0)


@dataclass(frozen=True)
class Fault:
    """One injected fault (see the module docstring, section Faults).

    ``kind`` one of ``FAULT_KINDS``; ``robot`` the robot it hits; active over the control steps
    whose end time t = k * dt lies in [start_s, start_s + duration_s). ``prob``: per IMU frame
    (imu_dropout) or per message copy (comm_burst), the probability that it is lost;
    ``scale``: delivered / commanded thrust (propulsion; 0 is dead); ``delay_s``: extra delay of
    the robot's messages (comm_delay, rounded to whole control periods).
    """

    kind: str
    robot: int
    start_s: float
    duration_s: float
    prob: float = 1.0
    scale: float = 0.0
    delay_s: float = 0.0

    @classmethod
    def parse(cls, spec: Fault | dict[str, Any], n_robots: int) -> Fault:
        """A validated ``Fault`` from a ``Fault`` or a dict of its fields (``ValueError``)."""
        if isinstance(spec, Fault):  # the fields of other kinds must hold their defaults
            own = ("kind", "robot", "start_s", "duration_s", *FAULT_KINDS.get(spec.kind, ()))
            spec = {
                f.name: getattr(spec, f.name)
                for f in dataclasses.fields(spec)
                if f.name in own or getattr(spec, f.name) != f.default
            }
        if not isinstance(spec, dict):
            raise ValueError(f"a fault must be a dict or a Fault, got {spec!r}")
        kind = spec.get("kind")
        if not isinstance(kind, str) or kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; allowed: {list(FAULT_KINDS)}")
        allowed = ("kind", "robot", "start_s", "duration_s", *FAULT_KINDS[kind])
        for key in spec:
            if key not in allowed:
                raise ValueError(f"fault {kind!r} takes the fields {list(allowed)}, got {key!r}")
        for key in ("robot", "start_s", "duration_s"):
            if key not in spec:
                raise ValueError(f"fault {kind!r} needs {key!r} (fields: {list(allowed)})")
        robot = spec["robot"]
        if isinstance(robot, bool) or not isinstance(robot, int | np.integer):
            raise ValueError(f"fault {kind!r}: robot must be an integer, got {robot!r}")
        if not 0 <= robot < n_robots:
            raise ValueError(f"fault {kind!r}: robot must be in 0..{n_robots - 1}, got {robot}")
        start = _check_finite_number("fault start_s", spec["start_s"], "a finite number >= 0 s")
        duration = _check_finite_number(
            "fault duration_s", spec["duration_s"], "a finite number > 0 s"
        )
        if start < 0 or duration <= 0:
            raise ValueError(
                f"fault {kind!r}: need start_s >= 0 and duration_s > 0, got {start}, {duration}"
            )
        values = {}
        for key, low, high, low_open in (
            ("prob", 0.0, 1.0, True),
            ("scale", 0.0, 1.0, False),
            ("delay_s", 0.0, math.inf, True),
        ):
            if key not in FAULT_KINDS[kind] or key not in spec:
                continue
            value = _check_finite_number(f"fault {key}", spec[key], f"a number in ({low}, {high}]")
            if not (low < value if low_open else low <= value) or value > high:
                bracket = "(" if low_open else "["
                raise ValueError(
                    f"fault {kind!r}: {key} must be in {bracket}{low}, {high}], got {value}"
                )
            values[key] = value
        if kind == "comm_delay" and "delay_s" not in values:
            raise ValueError("fault 'comm_delay' needs 'delay_s' > 0 s")
        return cls(kind, int(robot), start, duration, **values)

    def steps(self, dt_s: float) -> tuple[int, int]:
        """The control steps [first, end) it is active at (step k ends at k * dt_s)."""
        first = max(1, math.ceil(self.start_s / dt_s - 1e-9))
        end = max(first, math.ceil((self.start_s + self.duration_s) / dt_s - 1e-9))
        return first, end


def _parse_faults(faults: Any, n_robots: int) -> tuple[Fault, ...]:
    if faults is None:
        return ()
    if isinstance(faults, dict | Fault) or not isinstance(faults, list | tuple):
        raise ValueError(f"faults must be None or a list of dicts (or Faults), got {faults!r}")
    return tuple(Fault.parse(f, n_robots) for f in faults)


def _parse_release_at(release_at: Any, n_robots: int, dt_s: float) -> dict[int, int]:
    """``release_at`` as {robot: the control step at whose end it lets go} (``ValueError``)."""
    allowed = (
        f"None or a list of (robot, time_s) pairs, robot in 0..{n_robots - 1} at most once, "
        f"time_s a finite number >= 0"
    )
    if release_at is None:
        return {}
    if not isinstance(release_at, list | tuple):
        raise ValueError(f"release_at must be {allowed}, got {release_at!r}")
    steps: dict[int, int] = {}
    for pair in release_at:
        if not isinstance(pair, list | tuple) or len(pair) != 2:
            raise ValueError(f"release_at must be {allowed}, got the entry {pair!r}")
        robot, time_s = pair
        if isinstance(robot, bool) or not isinstance(robot, int | np.integer):
            raise ValueError(f"release_at: robot must be an integer, got {robot!r}")
        if not 0 <= robot < n_robots:
            raise ValueError(f"release_at: robot must be in 0..{n_robots - 1}, got {robot}")
        if int(robot) in steps:
            raise ValueError(f"release_at names robot {robot} twice; a robot lets go once")
        time_s = _check_finite_number("release_at time_s", time_s, "a finite number >= 0 s")
        if time_s < 0:
            raise ValueError(f"release_at time_s must be a finite number >= 0 s, got {time_s}")
        # The first control instant k * dt at or after time_s (k >= 1: never at reset).
        steps[int(robot)] = max(1, math.ceil(time_s / dt_s - 1e-9))
    return steps


class CargoTransport:
    """The world, sensors, channel, estimators and the robots' own navigation, with no
    multi-agent API: ``reset(rng)`` then ``step(actions)`` with an (n_robots, 8) array.

    The arguments are those of ``AstrobeeCargoEnv`` (see the module docstring) that concern the
    physics, estimation and rewards; they are validated here.
    """

    def __init__(
        self,
        n_robots: int = 2,
        trajectory: str = "figure8_yaw",
        fast: bool = False,
        noise: str = "nominal",
        cargo_mass_kg: float | tuple[float, float] = 5.0,
        cargo_com_m: tuple[float, float, float] | None = None,
        cargo_inertia: tuple[float, float, float, float, float, float] | None = None,
        comm_latency: float = 0.0,
        comm_drop: float = 0.0,
        comm_noise: tuple[float, float] = (0.0, 0.0),
        control_hz: float = CONTROL_HZ,
        frame_skip: int | None = None,
        w_track: float = 1.0,
        w_effort: float = 0.01,
        w_info: float = 0.0,
        w_contact: float = 1.0,
        shared_reward: float = 1.0,
        observe_estimates: bool = True,
        estimators: bool = True,
        estimator_kwargs: dict[str, Any] | None = None,
        faults: list[dict[str, Any] | Fault] | None = None,
        release_at: Any = None,
    ) -> None:
        if isinstance(n_robots, bool) or not isinstance(n_robots, int | np.integer):
            raise ValueError(f"n_robots must be an integer in 1..{MAX_ROBOTS}, got {n_robots!r}")
        if not 1 <= n_robots <= MAX_ROBOTS:
            raise ValueError(f"n_robots must be in 1..{MAX_ROBOTS}, got {n_robots}")
        _check_choice("trajectory", trajectory, Trajectory.NAMES)
        for name, flag in (
            ("fast", fast),
            ("observe_estimates", observe_estimates),
            ("estimators", estimators),
        ):
            if not isinstance(flag, bool | np.bool_):
                raise ValueError(f"{name} must be True or False, got {flag!r}")
        _check_choice("noise profile", noise, NOISE_PROFILES)
        if observe_estimates and not estimators:
            raise ValueError("observe_estimates=True needs estimators=True")
        self.n_robots = int(n_robots)
        self.faults = _parse_faults(faults, self.n_robots)
        self.trajectory_name = trajectory
        self.fast = bool(fast)
        self.noise = noise
        self.profile = get_noise_profile(noise)
        self.observe_estimates = bool(observe_estimates)
        self.use_estimators = bool(estimators)
        self.world = World(self.n_robots)
        self._set_cargo_args(cargo_mass_kg, cargo_com_m, cargo_inertia)

        low_hz, high_hz = CONTROL_HZ_LIMITS
        allowed_hz = f"a number of Hz in [{low_hz}, {high_hz}]"
        control_hz = _check_finite_number("control_hz", control_hz, allowed_hz)
        if not low_hz <= control_hz <= high_hz:
            raise ValueError(f"control_hz must be {allowed_hz}, got {control_hz}")
        self.control_hz = control_hz
        self.dt_s = 1.0 / control_hz
        mjcf_timestep = float(self.world.model.opt.timestep)
        if frame_skip is None:
            frame_skip = max(1, math.ceil(self.dt_s / mjcf_timestep - 1e-9))
        if isinstance(frame_skip, bool) or not isinstance(frame_skip, int | np.integer):
            raise ValueError(f"frame_skip must be None or a positive integer, got {frame_skip!r}")
        if frame_skip < 1 or self.dt_s / frame_skip > MAX_TIMESTEP_S:
            raise ValueError(
                f"frame_skip must be a positive integer with control period / frame_skip <= "
                f"{MAX_TIMESTEP_S} s, got {frame_skip} at {control_hz} Hz"
            )
        self.frame_skip = int(frame_skip)
        # The control period is exact: the physics step is the period over frame_skip.
        self.world.model.opt.timestep = self.dt_s / self.frame_skip
        # The world with every robot holding: each episode starts in it (a release rebuilds the
        # world without the robot, see _release), and state() keeps its layout.
        self._full_world = self.world
        self._full_data = mujoco.MjData(self.world.model)
        # Each fault with the control steps [first, end) it is active at.
        self._fault_windows = [(f, *f.steps(self.dt_s)) for f in self.faults]
        self.release_steps = _parse_release_at(release_at, self.n_robots, self.dt_s)

        latency = _check_finite_number(
            "comm_latency", comm_latency, f"a latency in [0, {MAX_COMM_LATENCY_S}] s"
        )
        if not 0.0 <= latency <= MAX_COMM_LATENCY_S:
            raise ValueError(
                f"comm_latency must be a latency in [0, {MAX_COMM_LATENCY_S}] s, got {latency}"
            )
        allowed_noise = f"two numbers (force N, moment N m) in [0, {MAX_COMM_NOISE}]"
        noise_std = _check_finite_array(
            "comm_noise (the channel's noise_std)", comm_noise, (2,), allowed_noise
        )
        if np.any(noise_std < 0) or np.any(noise_std > MAX_COMM_NOISE):
            raise ValueError(f"comm_noise (noise_std) must be {allowed_noise}, got {comm_noise!r}")
        self.comm_args = (latency, comm_drop, tuple(noise_std))
        CommChannel(self.n_robots, *self.comm_args, self.dt_s, np.random.default_rng(0))

        self.weights = {}
        allowed_w = f"a number in [-{MAX_REWARD_WEIGHT:g}, {MAX_REWARD_WEIGHT:g}]"
        for term, weight in zip(REWARD_TERMS, (w_track, w_effort, w_info, w_contact), strict=True):
            self.weights[term] = _check_finite_number(f"w_{term}", weight, allowed_w)
            if abs(self.weights[term]) > MAX_REWARD_WEIGHT:
                raise ValueError(f"w_{term} must be {allowed_w}, got {weight}")
        self._weights = [self.weights[t] for t in REWARD_TERMS]
        self.shared_reward = _check_finite_number(
            "shared_reward", shared_reward, "a number in [0, 1]"
        )
        if not 0.0 <= self.shared_reward <= 1.0:
            raise ValueError(f"shared_reward must be a number in [0, 1], got {shared_reward}")

        if estimator_kwargs is not None and not isinstance(estimator_kwargs, dict):
            raise ValueError(f"estimator_kwargs must be a dict or None, got {estimator_kwargs!r}")
        p = self.profile
        self.estimator_kwargs = {
            **estimator_noise_kwargs(p),
            "peer_noise_std": tuple(float(x) for x in noise_std),
            **(estimator_kwargs or {}),
        }
        self.trajectory = Trajectory(trajectory, fast=self.fast)
        self.robots = [self.world.robot_model(i) for i in range(self.n_robots)]
        self.thrust_limits = np.array([r.thrust_limit for r in self.robots])
        self.joint_ranges = np.array([r.joint_range for r in self.robots])
        self._bind_world(self._full_world, self._full_data)
        # Robot i's handrail (its grasp site on the cargo) in the cargo frame: known geometry.
        self.handrail_pose = [
            (_quat_to_mat(self.model.site_quat[site]), self.model.site_pos[site].copy())
            for site in self.world.handrail_sites
        ]
        self._handrail_rows = [
            (as_rows(rot), tuple(pos.tolist())) for rot, pos in self.handrail_pose
        ]
        self.obs_layout = observation_layout(self.n_robots, self.observe_estimates)
        # Per robot: the peer in each of its peer slots (increasing index, skipping itself).
        self._peer_slots = [
            [j for j in range(self.n_robots) if j != i] for i in range(self.n_robots)
        ]
        self.obs_dim = self.obs_layout["all"].stop
        full = self._full_world.model
        self.state_dim = 1 + full.nq + full.nv + 13 * (full.nbody - 1)
        self.state_dim += 10 + 21 + 2 * self.n_robots + self.n_robots
        if self.use_estimators:  # fail early on bad estimator settings
            self._make_estimators()
        self.step_count = 0
        self._ready = False
        self._ref_cache: list | None = None

    # ------------------------------------------------------------------ arguments
    def _set_cargo_args(self, mass_kg: Any, com_m: Any, inertia: Any) -> None:
        low_kg, high_kg = CARGO_MASS_LIMITS_KG
        allowed = f"a mass in [{low_kg}, {high_kg}] kg, or a range (low, high) within it"
        if isinstance(mass_kg, tuple | list | np.ndarray):
            bounds = _check_finite_array("cargo_mass_kg", mass_kg, (2,), allowed)
        else:
            bounds = np.full(2, _check_finite_number("cargo_mass_kg", mass_kg, allowed))
        if not low_kg <= bounds[0] <= bounds[1] <= high_kg:
            raise ValueError(f"cargo_mass_kg must be {allowed}, low <= high, got {mass_kg!r}")
        self.cargo_mass_range = bounds
        # The cargo's mass lies in its bag (the World's, chosen by the number of robots): its
        # centre of mass too, and no mass is farther than the bag's diagonal from an axis through
        # it, so each principal moment is at most m * diagonal^2.
        half_box = 0.5 * self.world.cargo_size_m
        diagonal_m = math.hypot(*self.world.cargo_size_m)
        if com_m is None:
            self.cargo_com = None
        else:
            allowed = f"None or 3 numbers (m) within the bag, |c| <= {tuple(half_box)}"
            com = _check_finite_array("cargo_com_m", com_m, (3,), allowed)
            if np.any(np.abs(com) > half_box):
                raise ValueError(f"cargo_com_m must be {allowed}, got {com_m!r}")
            self.cargo_com = com
        if inertia is None:
            self.cargo_inertia = None
        else:
            vec = _check_finite_array(
                "cargo_inertia",
                inertia,
                (6,),
                "None or 6 finite numbers (I_xx, I_yy, I_zz, I_xy, I_xz, I_yz) about the centre "
                "of mass",
            )
            tensor = vec_to_inertia(vec)
            try:  # realisable about the centre of mass, whatever the mass
                check_physical(params_from_mass_com_inertia(1.0, np.zeros(3), tensor))
            except ValueError as err:
                raise ValueError(f"cargo_inertia is not a physical inertia tensor: {err}") from err
            max_moment = bounds[0] * diagonal_m**2
            if np.linalg.eigvalsh(tensor)[-1] > max_moment:
                raise ValueError(
                    f"cargo_inertia: a principal moment exceeds m * d^2 = {max_moment:.3g} kg m^2 "
                    f"(mass {bounds[0]} kg within the bag, diagonal d = {diagonal_m:.3f} m), "
                    f"got {inertia!r}"
                )
            self.cargo_inertia = tensor

    def _sample_cargo(self, rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
        low, high = self.cargo_mass_range
        mass = float(rng.uniform(low, high)) if high > low else float(low)
        if self.cargo_com is None:
            com = rng.uniform(-CARGO_COM_SPREAD_M, CARGO_COM_SPREAD_M, 3)
        else:
            com = self.cargo_com.copy()
        if self.cargo_inertia is None:
            inertia = self.world.uniform_cargo_inertia(mass)
        else:
            inertia = self.cargo_inertia.copy()
        return mass, com, inertia

    def _make_estimators(self) -> list[CargoEstimator]:
        out = []
        for i in range(self.n_robots):
            peers = [j for j in range(self.n_robots) if j != i]
            # The grasp layout (which handrails the team holds) is known geometry, like the
            # handrail poses the observations use; estimating it from fixes biases early updates.
            kwargs = {
                "relative_grasps": {j: self.world.relative_grasp(i, j) for j in peers},
                **self.estimator_kwargs,
            }
            try:
                est = CargoEstimator(self.robots[i], i, peers, self.dt_s, **kwargs)
            except TypeError as err:
                raise ValueError(f"bad estimator_kwargs {self.estimator_kwargs!r}: {err}") from err
            out.append(est)
        return out

    def _bind_world(self, world: World, data: mujoco.MjData) -> None:
        """Simulate ``world`` (with its state in ``data``): the robots it holds act, and the
        indices into its model are refreshed."""
        self.world, self.model, self.data = world, world.model, data
        self._bind_views()
        self.holding = world.holding
        # Index of the holding robots' rows in per-robot arrays: a slice (no copy) for all.
        everyone = len(self.holding) == self.n_robots
        self._rows: slice | list[int] = slice(None) if everyone else list(self.holding)
        self._thrust_ctrl = np.array([h.thrust_actuators for h in world.robots], dtype=int)
        self._arm_ctrl = np.array([h.arm_actuators for h in world.robots], dtype=int)
        # Which robot (index), the cargo (n_robots) or the module (-1) each geom belongs to.
        self._geom_owner = np.full(self.model.ngeom, -1)
        for h in world.robots:
            self._geom_owner[list(h.robot_geoms)] = h.index
        self._geom_owner[self.model.geom_bodyid == world.cargo_body] = self.n_robots
        self._wall_geom = np.zeros(self.model.ngeom, dtype=bool)
        self._wall_geom[list(world.wall_geoms)] = True
        # Where this world's qpos, qvel and bodies go in state()'s fixed layout.
        self._state_qpos, self._state_qvel, self._state_body = world.layout_in(self._full_world)

    _VIEWS = ("_qpos", "_qvel", "_ctrl", "_xpos", "_xmat", "_warnings")

    def _bind_views(self) -> None:
        """Views of the data's arrays used every step (each property access builds a new one)."""
        data = self.data
        self._qpos, self._qvel, self._ctrl = data.qpos, data.qvel, data.ctrl
        self._xpos, self._xmat, self._warnings = data.xpos, data.xmat, data.warning.number

    # A copy (copy.deepcopy, pickle) gets its own MjData: the views are rebound to it, not copied
    # as detached arrays.
    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k not in self._VIEWS}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._bind_views()

    # ------------------------------------------------------------------ episode
    def reset(self, rng: np.random.Generator) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """Start an episode; sensor, channel and cargo generators are spawned from ``rng``.
        Returns the observations (n_robots, obs_dim) and infos."""
        sensor_rng, comm_rng, cargo_rng = rng.spawn(3)
        # Spawned only with faults, so that a run without them draws as it always did.
        self.fault_rng = rng.spawn(1)[0] if self.faults else None
        self.fault_counts = {k: np.zeros(self.n_robots, dtype=np.int64) for k in FAULT_COUNTERS}
        self.cargo = self._sample_cargo(cargo_rng)
        if self.world is not self._full_world:  # robots let go last episode
            self._bind_world(self._full_world, self._full_data)
        self.released_at_s: dict[int, float] = {}
        self.released_momentum: dict[int, np.ndarray] = {}
        self.world.set_cargo(*self.cargo)
        self.world.reset_data(self.data)
        self.true_params = self.world.cargo_params()
        self.true_params_grasp = [
            self.world.cargo_params_in_grasp_frame(i) for i in range(self.n_robots)
        ]
        self.sensors = SensorSuite(self.world, self.profile, sensor_rng)
        self.channel = CommChannel(
            self.n_robots, *self.comm_args, self.dt_s, comm_rng, fault_rng=self.fault_rng
        )
        for fault, first, end in self._fault_windows:
            if fault.kind == "comm_burst":
                self.channel.add_burst(fault.robot, first, end, fault.prob)
            elif fault.kind == "comm_delay":
                self.channel.add_delay(fault.robot, first, end, fault.delay_s)
        self.estimators = self._make_estimators() if self.use_estimators else []
        self.navigators = [BaseNavigator(r, self.dt_s, self.profile) for r in self.robots]
        self.arm_targets = np.tile(np.asarray(ARM_DEPLOYED_RAD), (self.n_robots, 1))
        self.peer_msgs: list[dict[int, Any]] = [{} for _ in range(self.n_robots)]
        self.step_count = 0
        self._ready = True

        packets = self._read_at_rest()
        self._update_estimators(packets, np.zeros((self.n_robots, 6)), 0)
        for nav, packet in zip(self.navigators, packets, strict=True):
            nav.reset(packet)
        self.packets = packets
        self._refresh_estimates()
        self._log_std_sum = self._estimate_log_std_sums()
        everyone = self.holding
        obs = self._get_obs(everyone)
        zero_terms = {t: [0.0] * self.n_robots for t in REWARD_TERMS}
        none = np.zeros(self.n_robots, dtype=int)
        infos = self._get_infos(zero_terms, none, none, None, everyone, ())
        return obs, infos

    def _read_at_rest(self) -> list[SensorPacket]:
        """The first reading: the robots rest for one period before the episode starts, so the
        IMU reads its noise only, and a localization fix and the encoders come with it."""
        t0 = float(self.data.time)
        self.sensors.begin_period(self.data)
        self.data.time = t0 + self.dt_s
        try:
            packets = self.sensors.read(self.data, 0)
        finally:
            self.data.time = t0
        return packets  # every robot holds at reset: one packet per robot, in index order

    def step(self, actions: np.ndarray) -> StepResult:
        """Advance one control period with ``actions`` (n_robots, 8) in [-1, 1] (clipped); the
        rows of robots that have let go of the cargo are ignored."""
        if not self._ready:
            raise RuntimeError("call reset() before step(), and again after the episode ended")
        actions = np.asarray(actions, dtype=float)
        if actions.shape != (self.n_robots, ACTION_DIM):
            raise ValueError(
                f"actions must have shape {(self.n_robots, ACTION_DIM)}, got {actions.shape}"
            )
        acting = self.holding  # the robots of this step, those letting go at its end included
        rows = self._rows  # their rows: every row (a slice) or a list
        acting_actions = actions[rows]
        if not np.isfinite(acting_actions).all():
            finite_rows = np.isfinite(acting_actions).all(axis=1)
            raise ValueError(
                f"actions of robot {acting[int(np.argmin(finite_rows))]} are not all finite"
            )
        acting_clipped = np.minimum(np.maximum(acting_actions, -1.0), 1.0)  # np.clip, faster
        clipped = np.zeros_like(actions)
        clipped[rows] = acting_clipped
        n_clipped = np.zeros(self.n_robots, dtype=int)
        n_clipped[rows] = (acting_clipped != acting_actions).sum(axis=1)
        self.step_count += 1
        k = self.step_count

        commands = self._apply_actions(clipped)
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        mujoco.mj_forward(self.model, self.data)
        finite = self._physics_finite()
        packets = self._read_sensors(k)
        self._update_estimators(packets, commands, k)
        for i in acting:
            self.navigators[i].update(packets[i])
        self.packets = packets

        robot_contacts, cargo_contacts = self._wall_contacts()
        # A release due with a non-finite state does not happen: the episode ends (non_finite).
        released = ()
        if self.release_steps and finite:
            released = tuple(i for i in acting if self.release_steps.get(i) == k)
        if released:
            self._release(released)
        obs = self._get_obs(acting)
        if not np.isfinite(obs).all():
            finite = False
            obs = np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0)
        reason = None
        if not finite:
            reason = "non_finite"
        elif robot_contacts.sum() + cargo_contacts > 0:
            reason = "wall_contact"
        terms, rewards = self._get_rewards(clipped, robot_contacts, cargo_contacts, finite, acting)
        infos = self._get_infos(
            terms, n_clipped, robot_contacts + cargo_contacts, reason, acting, released
        )
        if reason is not None or not self.holding:
            self._ready = False
        return StepResult(obs, rewards, reason is not None, reason, infos, released)

    def _release(self, released: tuple[int, ...]) -> None:
        """The robots ``released`` let go of the cargo now (end of a control step): the world is
        rebuilt without them, the others' state carried over unchanged (``World.load_state``);
        they leave the channel, and the others' estimators stop expecting their messages."""
        for i in released:
            bodies = self.world.handle(i).robot_bodies
            self.released_momentum[i] = self.world.momentum(self.data, bodies)
            self.released_at_s[i] = float(self.data.time)
        world = self.world.without_robots(released)
        data = mujoco.MjData(world.model)
        world.load_state(self.world, self.data, data)
        self._bind_world(world, data)
        self.sensors = SensorSuite(world, self.profile, self.sensors.rng)
        for i in released:
            self.channel.disconnect(i)
        for i in self.holding:
            for j in released:
                self.peer_msgs[i].pop(j, None)
            if self.estimators:
                self.estimators[i].set_peers([j for j in self.holding if j != i])

    # ------------------------------------------------------------------ one step, in order
    def _apply_actions(self, clipped: np.ndarray) -> np.ndarray:
        """Scale to commands, write d.ctrl (thrust with actuation noise) of the robots holding
        the cargo, start the period. Returns the thrust commands (n_robots, 6) each robot knows
        it sent (zeros for those that have let go)."""
        commands = clipped[:, :6] * self.thrust_limits
        # The servo targets, joint by joint on floats (four numbers: numpy's overhead dominates).
        max_move = ARM_SPEED_RADPS * self.dt_s
        self.arm_targets = np.array(
            [
                [
                    _arm_target(current, deployed + ARM_OFFSET_RAD * action, max_move, low, high)
                    for action, current, deployed, (low, high) in zip(
                        actions, currents, ARM_DEPLOYED_RAD, ranges, strict=True
                    )
                ]
                for actions, currents, ranges in zip(
                    clipped[:, 6:].tolist(),
                    self.arm_targets.tolist(),
                    self.joint_ranges.tolist(),
                    strict=True,
                )
            ]
        )
        rows = self._rows
        delivered = self.sensors.actuate(commands[rows])  # row k: robot holding[k]
        weakened = set()
        for fault in self._active_faults("propulsion", self.step_count):
            if fault.robot in self.holding:
                delivered[self.holding.index(fault.robot)] *= fault.scale
                weakened.add(fault.robot)
        if weakened:
            self.fault_counts["propulsion_steps"][list(weakened)] += 1
        self._ctrl[self._thrust_ctrl] = delivered
        self._ctrl[self._arm_ctrl] = self.arm_targets[rows]
        self.sensors.begin_period(self.data)
        return commands

    def _physics_finite(self) -> bool:
        unstable = self._warnings[_BAD_QACC] > 0
        return bool(
            np.isfinite(self._qpos).all() and np.isfinite(self._qvel).all() and not unstable
        )

    def _read_sensors(self, k: int) -> list[SensorPacket]:
        """Every robot's packet (None for a robot that has let go), with the faults of step ``k``
        applied (after the sensor noise draws, so a run with faults draws the same noise as one
        without)."""
        packets: list[SensorPacket | None] = [None] * self.n_robots
        for h, packet in zip(self.world.robots, self.sensors.read(self.data, k), strict=True):
            packets[h.index] = packet
        for fault in self._active_faults("imu_dropout", k):
            i = fault.robot
            if packets[i] is None or packets[i].accel_imu is None:
                continue  # let go, or two overlapping dropouts
            if fault.prob < 1.0 and self.fault_rng.random() >= fault.prob:
                continue
            packets[i] = dataclasses.replace(packets[i], accel_imu=None, gyro_imu=None)
            self.fault_counts["imu_frames_missing"][i] += 1
        for fault in self._active_faults("localization_outage", k):
            i = fault.robot
            if packets[i] is not None and packets[i].base_pos_world is not None:
                packets[i] = dataclasses.replace(
                    packets[i], base_pos_world=None, base_quat_world=None
                )
                self.fault_counts["fixes_missing"][i] += 1
        return packets

    def _active_faults(self, kind: str, k: int) -> list[Fault]:
        """The faults of ``kind`` active at control step ``k``."""
        if not self._fault_windows:
            return []
        return [f for f, first, end in self._fault_windows if f.kind == kind and first <= k < end]

    def _fault_infos(self) -> list[dict[str, Any]]:
        """Every robot's injected-fault counters (episode totals) and the kinds active now."""
        if not self._fault_windows:  # none injected: every counter stays 0
            return [{**_NO_FAULT_COUNTS, "active": []} for _ in range(self.n_robots)]
        counts = {k: v.tolist() for k, v in self.fault_counts.items()}
        counts.update({f"messages_{k}": v.tolist() for k, v in self.channel.fault_stats.items()})
        active: list[list[str]] = [[] for _ in range(self.n_robots)]
        k = self.step_count
        for f, first, end in self._fault_windows:
            if first <= k < end:
                active[f.robot].append(f.kind)
        return [
            {**{name: c[i] for name, c in counts.items()}, "active": active[i]}
            for i in range(self.n_robots)
        ]

    def _update_estimators(self, packets: list[SensorPacket], commands: np.ndarray, k: int) -> None:
        """Each estimator ingests its own packet and command; messages go through the channel;
        what is due is delivered; each estimator updates with its complete instants."""
        if not self.estimators:
            return
        for i in self.holding:
            est, packet, command = self.estimators[i], packets[i], commands[i]
            msg = est.step(
                k,
                packet.accel_imu,
                packet.gyro_imu,
                packet.joint_pos_rad,
                command,
                packet.base_pos_world,
                packet.base_quat_world,
            )
            if msg is not None:
                self.channel.send(msg, k)
        for receiver, msgs in self.channel.deliver(k).items():
            for msg in msgs:
                self.estimators[receiver].receive(msg)
                latest = self.peer_msgs[receiver].get(msg.sender)
                if latest is None or msg.stamp > latest.stamp:
                    self.peer_msgs[receiver][msg.sender] = msg
        updated = [self.estimators[i].process() > 0 for i in self.holding]
        if any(updated):
            self._refresh_estimates()

    def _refresh_estimates(self) -> None:
        if not self.estimators:
            self.est_mean, self.est_std, self.est_errors = [], [], []
            return
        self.est_mean = [est.params_mean() for est in self.estimators]
        self.est_std = [est.params_std() for est in self.estimators]
        self._log_std_now = np.log(np.maximum(np.array(self.est_std), LOG_STD_FLOOR)).sum(axis=1)
        # Every robot's errors in one call per kind (the same values robot by robot).
        means, truths = np.array(self.est_mean), np.array(self.true_params_grasp)
        self.est_errors = [
            {"mass_rel_err": mass, "com_err_m": com, "principal_rel_err": principal}
            for mass, com, principal in zip(
                mass_rel_error(means, truths).tolist(),
                com_error_m(means, truths).tolist(),
                principal_rel_errors(means, truths).tolist(),
                strict=True,
            )
        ]

    def _estimate_log_std_sums(self) -> np.ndarray:
        """Sum of the log standard deviations of each robot's estimate (as of the last refresh)."""
        if not self.estimators:
            return np.zeros(self.n_robots)
        return self._log_std_now

    def _wall_contacts(self) -> tuple[np.ndarray, int]:
        """Contacts with the module per robot, and those of the cargo."""
        ncon = self.data.ncon
        per_robot = np.zeros(self.n_robots, dtype=int)
        if ncon == 0:
            return per_robot, 0
        geoms = self.data.contact.geom[:ncon]
        wall = self._wall_geom[geoms]
        owner = self._geom_owner[geoms]
        # The module is static: a wall contact is one with exactly one wall geom.
        hit = wall[:, 0] ^ wall[:, 1]
        other = np.where(wall[:, 0], owner[:, 1], owner[:, 0])[hit]
        per_robot += np.bincount(other[other < self.n_robots], minlength=self.n_robots)
        return per_robot, int(np.sum(other == self.n_robots))

    # ------------------------------------------------------------------ observations
    def reference(self) -> Reference:
        """The cargo reference at the current time (evaluated once per time)."""
        cache = self._reference_cache()
        if cache[2] is None:
            cache[2] = cache[1].to_reference()
        return cache[2]

    def _reference_values(self) -> ReferenceValues:
        """The reference at the current time on floats (evaluated once per time)."""
        return self._reference_cache()[1]

    def _reference_cache(self) -> list:
        """[time, its ReferenceValues, its Reference once asked for]."""
        t = float(self.data.time)
        if self._ref_cache is None or self._ref_cache[0] != t:
            self._ref_cache = [t, self.trajectory.values(t), None]
        return self._ref_cache

    def _base_reference(
        self, i: int, ref: ReferenceValues, joint_pos: list[float]
    ) -> tuple[tuple, tuple, tuple]:
        """Robot i's base pose and velocity if the cargo were on its reference, grasp rigid at
        the arm angles ``joint_pos``: rotation (rows), position, velocity (world), floats."""
        grasp_rot, grasp_pos = grasp_pose_rows(self.robots[i], joint_pos)
        rot_ch, pos_ch = self._handrail_rows[i]
        rot = m_mt(m_m(ref.rot, rot_ch), grasp_rot)
        pos = v_sub(v_add(ref.pos, m_v(ref.rot, pos_ch)), m_v(rot, grasp_pos))
        vel = v_add(ref.vel, v_cross(ref.w, v_sub(pos, ref.pos)))
        return rot, pos, vel

    def _get_obs(self, robots: tuple[int, ...]) -> np.ndarray:
        """Observations of ``robots`` (the others' rows zeros). A peer that has let go of the
        cargo has its slot zeroed: its messages are forgotten (``_release``).

        Each row is assembled on floats in the order of ``observation_layout``."""
        ref = self._reference_values()
        obs = np.zeros((self.n_robots, self.obs_dim))
        step_count, dt = self.step_count, self.dt_s
        for i in robots:
            rot, base_pos, base_vel, w = self.navigators[i].state_rows()
            joint_pos = self.packets[i].joint_pos_rad.tolist()
            rot_ref, pos_ref, vel_ref = self._base_reference(i, ref, joint_pos)
            row = [
                *mt_v(rot, v_sub(base_pos, pos_ref)),
                *mt_v(rot, v_sub(base_vel, vel_ref)),
                *_rotvec(mt_m(rot_ref, rot)),
                *w,
                *joint_pos,
                *self.arm_targets[i].tolist(),
                *mt_v(rot, v_sub(ref.pos, base_pos)),
                *mt_v(rot, ref.vel),
                *mt_v(rot, ref.acc),
                *mt_v(rot, ref.w),
                *mt_v(rot, ref.wd),
                ref.pan,
                ref.pan_rate,
            ]
            latest = self.peer_msgs[i]
            for j in self._peer_slots[i]:
                msg = latest.get(j)
                if msg is None:
                    row += _EMPTY_PEER_SLOT
                    continue
                wrench = msg.wrench_world.tolist()
                row += mt_v(rot, wrench[:3])
                row += mt_v(rot, wrench[3:])
                row += ((step_count - msg.stamp) * dt, 1.0)
            if self.observe_estimates:
                row += self.est_mean[i].tolist()
                row += self.est_std[i].tolist()
            obs[i] = row
        return obs

    # ------------------------------------------------------------------ rewards, infos
    def tracking_error(self) -> tuple[float, float]:
        """True cargo frame position error (m) and rotation angle error (rad)."""
        b = self.world.cargo_body
        ref = self._reference_values()
        rot = as_rows(self._xmat[b].reshape(3, 3))
        pos_err = norm3(v_sub(self._xpos[b].tolist(), ref.pos))
        return pos_err, norm3(_rotvec(mt_m(ref.rot, rot)))

    def _get_rewards(
        self,
        clipped: np.ndarray,
        robot_contacts: np.ndarray,
        cargo_contacts: int,
        finite: bool,
        robots: tuple[int, ...],
    ) -> tuple[dict[str, list[float]], np.ndarray]:
        """Every reward term per robot, weighted and mixed (team vs individual), and their sum
        per robot; the team of this step is ``robots`` (the others' rows zeros)."""
        n = self.n_robots
        if finite:
            pos_err, angle_err = self.tracking_error()
            track = -(pos_err + ROTATION_WEIGHT_M_PER_RAD * angle_err)
        else:
            track = 0.0
        effort = -(clipped**2).sum(axis=1)
        log_std = self._estimate_log_std_sums()
        info = (self._log_std_sum - log_std).tolist()
        self._log_std_sum = log_std
        if not all(map(math.isfinite, info)):
            info = [0.0] * n
        # Rows in REWARD_TERMS order: (track, effort, info, contact) per robot and for the team,
        # on floats (a few numbers: numpy's per-call overhead would dominate).
        robot_contacts = robot_contacts.tolist()
        contact = [-(c + cargo_contacts) for c in robot_contacts]
        individual = [[float(track)] * n, effort.tolist(), info, contact]
        team = [_mean(values, robots) for values in individual]
        team[0] = track
        team[3] = -float(sum(robot_contacts) + cargo_contacts)
        s = self.shared_reward
        mask = [1.0 if i in robots else 0.0 for i in range(n)]
        mixed = [
            [
                (weight * m) * (s * team_term + (1.0 - s) * x)
                for m, x in zip(mask, term, strict=True)
            ]
            for weight, team_term, term in zip(self._weights, team, individual, strict=True)
        ]
        rewards = [sum(values) for values in zip(*mixed, strict=True)]  # 0 + track + ... + contact
        return dict(zip(REWARD_TERMS, mixed, strict=True)), np.array(rewards)

    def _get_infos(
        self,
        terms: dict[str, list[float]],
        n_clipped: np.ndarray,
        wall_contacts: np.ndarray,
        reason: str | None,
        robots: tuple[int, ...],
        released: tuple[int, ...],
    ) -> list[dict[str, Any] | None]:
        """Infos of ``robots`` (None for the others); ``released``: those letting go now."""
        infos: list[dict[str, Any] | None] = [None] * self.n_robots
        comm = dict(self.channel.stats)
        rewards = [terms[t] for t in REWARD_TERMS]
        n_clipped, wall_contacts = n_clipped.tolist(), wall_contacts.tolist()
        faults = self._fault_infos()
        time_s = float(self.data.time)
        for i in robots:
            info: dict[str, Any] = {key: r[i] for key, r in zip(REWARD_KEYS, rewards, strict=True)}
            if i in released:
                info["released_momentum"] = self.released_momentum[i].copy()
            info.update(
                termination_reason=reason or ("released" if i in released else None),
                releases=len(self.released_at_s),
                holding=list(self.holding),
                time_s=time_s,
                clipped_actions=n_clipped[i],
                wall_contacts=wall_contacts[i],
                true_params=self.true_params_grasp[i].copy(),
                comm=comm,
                faults=faults[i],
            )
            if self.estimators:
                info.update(
                    estimate=self.est_mean[i].copy(),
                    estimate_std=self.est_std[i].copy(),
                    estimator=self.estimators[i].counters,
                    **self.est_errors[i],
                )
            infos[i] = info
        return infos

    def state(self) -> np.ndarray:
        """The full true state (see the module docstring, section State)."""
        m, d = self.model, self.data
        full = self._full_world.model
        qpos, qvel = np.zeros(full.nq), np.zeros(full.nv)
        qpos[self._state_qpos] = d.qpos
        qvel[self._state_qvel] = d.qvel
        bodies = np.zeros((full.nbody, 13))
        vel = np.zeros(6)
        for b in range(1, m.nbody):
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, b, vel, 0)
            bodies[self._state_body[b]] = np.concatenate((d.xpos[b], d.xquat[b], vel[3:], vel[:3]))
        holding = np.zeros(self.n_robots)
        holding[list(self.holding)] = 1.0
        ref = self.reference()
        parts = [
            np.array([d.time]),
            qpos,
            qvel,
            bodies[1:].ravel(),
            self.true_params,
            ref.pos,
            ref.vel,
            ref.acc,
            _mat_to_quat(ref.rot),
            ref.w,
            ref.wd,
            np.array([ref.pan, ref.pan_rate]),
            (self.arm_targets * holding[:, None]).ravel(),
            holding,
        ]
        return np.concatenate(parts).astype(np.float64)


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


class AstrobeeCargoEnv(ParallelEnv):
    """PettingZoo ParallelEnv of ``CargoTransport``; see the module docstring."""

    metadata = {
        "name": "astrobee_cargo_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": round(CONTROL_HZ),  # round(1 / control period): 62 at 62.5 Hz
        "is_parallelizable": True,
    }

    def __init__(
        self,
        n_robots: int = 2,
        trajectory: str = "figure8_yaw",
        fast: bool = False,
        noise: str = "nominal",
        cargo_mass_kg: float | tuple[float, float] = 5.0,
        cargo_com_m: tuple[float, float, float] | None = None,
        cargo_inertia: tuple[float, float, float, float, float, float] | None = None,
        comm_latency: float = 0.0,
        comm_drop: float = 0.0,
        comm_noise: tuple[float, float] = (0.0, 0.0),
        control_hz: float = CONTROL_HZ,
        frame_skip: int | None = None,
        max_cycles: int | None = None,
        w_track: float = 1.0,
        w_effort: float = 0.01,
        w_info: float = 0.0,
        w_contact: float = 1.0,
        shared_reward: float = 1.0,
        observe_estimates: bool = True,
        estimators: bool = True,
        estimator_kwargs: dict[str, Any] | None = None,
        faults: list[dict[str, Any] | Fault] | None = None,
        release_at: Any = None,
        render_mode: str | None = None,
        render_width: int = 640,
        render_height: int = 480,
        render_camera: str = RENDER_CAMERA_TRACK,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"unknown render_mode {render_mode!r}; allowed: None, "
                f"{self.metadata['render_modes']}"
            )
        if render_mode == "human":
            _require_display()
        self.sim = CargoTransport(
            n_robots=n_robots,
            trajectory=trajectory,
            fast=fast,
            noise=noise,
            cargo_mass_kg=cargo_mass_kg,
            cargo_com_m=cargo_com_m,
            cargo_inertia=cargo_inertia,
            comm_latency=comm_latency,
            comm_drop=comm_drop,
            comm_noise=comm_noise,
            control_hz=control_hz,
            frame_skip=frame_skip,
            w_track=w_track,
            w_effort=w_effort,
            w_info=w_info,
            w_contact=w_contact,
            shared_reward=shared_reward,
            observe_estimates=observe_estimates,
            estimators=estimators,
            estimator_kwargs=estimator_kwargs,
            faults=faults,
            release_at=release_at,
        )
        if max_cycles is None:
            max_cycles = round(EPISODE_S * self.sim.control_hz)
        if isinstance(max_cycles, bool) or not isinstance(max_cycles, int | np.integer):
            raise ValueError(f"max_cycles must be None or a positive integer, got {max_cycles!r}")
        if max_cycles < 1:
            raise ValueError(f"max_cycles must be None or a positive integer, got {max_cycles}")
        self.max_cycles = int(max_cycles)
        for name, size, limit in (
            ("render_width", render_width, 1280),
            ("render_height", render_height, 720),
        ):
            if isinstance(size, bool) or not isinstance(size, int | np.integer):
                raise ValueError(f"{name} must be an integer in 1..{limit}, got {size!r}")
            if not 1 <= size <= limit:  # the MJCF's offscreen buffer
                raise ValueError(f"{name} must be an integer in 1..{limit}, got {size}")
        cameras = [self.sim.model.camera(c).name for c in range(self.sim.model.ncam)]
        if render_camera != RENDER_CAMERA_TRACK and render_camera not in cameras:
            raise ValueError(
                f"unknown render_camera {render_camera!r}; allowed: "
                f"{[RENDER_CAMERA_TRACK, *cameras]}"
            )
        self.render_mode = render_mode
        self.render_size = (int(render_height), int(render_width))
        self.render_camera = render_camera
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.sim.dt_s)}
        self.possible_agents = [f"astrobee_{i}" for i in range(self.sim.n_robots)]
        self.agents: list[str] = []
        self._index = {agent: i for i, agent in enumerate(self.possible_agents)}
        self.state_space = spaces.Box(-np.inf, np.inf, (self.sim.state_dim,), np.float64)
        low = np.full(self.sim.obs_dim, -np.inf)
        high = np.full(self.sim.obs_dim, np.inf)
        for name, sl in self.sim.obs_layout.items():
            if name.endswith("_valid"):
                low[sl], high[sl] = 0.0, 1.0
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
        if self._episode_over:
            raise RuntimeError(
                "the episode has ended (or reset() was never called): call reset() before step()"
            )
        live = self.agents[:]
        result = self.sim.step(self._action_array(actions))
        truncated = self.sim.step_count >= self.max_cycles
        released = {self.possible_agents[i] for i in result.released}
        reward_values = result.rewards.tolist()
        rewards = {a: reward_values[self._index[a]] for a in live}
        terminations = {a: result.terminated or a in released for a in live}
        truncations = dict.fromkeys(live, truncated)
        obs = self._by_agent(result.observations, live)
        infos = self._by_agent(result.infos, live)
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        if not self.agents:
            self._episode_over = True
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terminations, truncations, infos

    def _action_array(self, actions: dict[str, np.ndarray]) -> np.ndarray:
        """Every live agent's validated action in one array (rows of robots that have let go:
        zeros); actions given for agents no longer live are ignored, as PettingZoo's
        ``aec_to_parallel`` does."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict agent -> array, got {type(actions).__name__}")
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
