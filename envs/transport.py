"""The physics, sensing, estimation and rewards of the cargo transport, with no multi-agent API
(``CargoTransport``); ``AstrobeeCargoEnv`` in ``astrocargo.envs.cargo_transport`` is the
PettingZoo layer on top, and its docstring describes both."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from numba import njit

from astrocargo.agents.excitation import make_trajectory
from astrocargo.agents.trajectories import Reference
from astrocargo.envs.actions import (  # noqa: F401 (re-exported)
    ACTION_DIM,
    ARM_DEPLOYED,
    ARM_OFFSET_RAD,
    ARM_SPEED_RADPS,
    first_non_finite,
    scale_actions,
)
from astrocargo.envs.cargo import CARGO_COM_SPREAD_M, CargoDraw  # noqa: F401
from astrocargo.envs.comms import CommChannel
from astrocargo.envs.config import (
    REWARD_TERMS,
    EnvConfig,
)
from astrocargo.envs.estimation import (  # noqa: F401 (re-exported)
    LOG_STD_FLOOR,
    SENT_ARM_KEPT,
    TeamEstimation,
    make_estimators,
)
from astrocargo.envs.faults import (
    FAULT_COUNTERS,
    NO_FAULT_COUNTS,
    Fault,
    parse_release_at,
)
from astrocargo.envs.navigation import BaseNavigator
from astrocargo.envs.observations import ObservationBuilder, observation_layout
from astrocargo.envs.rewards import ROTATION_WEIGHT_M_PER_RAD, reward_terms
from astrocargo.envs.sensors import SensorReadings, SensorSuite, estimator_noise_kwargs
from astrocargo.envs.sensors import noise_profile as get_noise_profile
from astrocargo.envs.world import ARM_DEPLOYED_RAD, MAX_TIMESTEP_S, World
from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.geometry import log_so3, mat_to_quat, matmul3, quat_to_mat

REWARD_KEYS = tuple(f"reward_{t}" for t in REWARD_TERMS)  # their names in infos
# MuJoCo's instability warnings: on a bad qpos, qvel or qacc it resets the state to the model's
# initial one (and counts the warning), so after one the physics no longer continues.
_UNSTABLE = np.array(
    [int(getattr(mujoco.mjtWarning, f"mjWARN_BAD{x}")) for x in ("QPOS", "QVEL", "QACC")]
)
TERMINATION_REASONS = ("wall_contact", "non_finite", "released")  # "released": one agent


@njit(cache=True)
def all_finite(values):
    """Whether every entry of a contiguous array is finite (no temporary, unlike np.isfinite)."""
    for x in values.ravel():
        if not math.isfinite(x):
            return False
    return True


@njit(cache=True)
def thrust_saturation(actions: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """Per row, the share of the requested thrust a robot could not deliver: 1 - |a_c| / |a|
    over the six thrust entries of the action a as given and a_c as clipped to [-1, 1] (0 for
    a zero request), in [0, 1]."""
    wanted = np.sqrt((actions[:, :6] ** 2).sum(axis=1))
    delivered = np.sqrt((clipped[:, :6] ** 2).sum(axis=1))
    return np.where(wanted > 0, 1.0 - delivered / np.maximum(wanted, 1e-300), 0.0)


def tracking_errors(pos, rot, ref_pos, ref_rot):
    """Position error |p - p_ref| (m) and rotation angle error |log(R_ref^T R)| (rad)."""
    angle = log_so3(matmul3(ref_rot.T, rot))
    return np.linalg.norm(pos - ref_pos), np.linalg.norm(angle)


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


class CargoTransport:
    """The world, sensors, channel, estimators and the robots' own navigation, with no
    multi-agent API: ``reset(rng)`` then ``step(actions)`` with an (n_robots, 8) array.

    Takes an ``EnvConfig`` (or its keyword arguments); the rendering and ``max_cycles`` fields
    are the PettingZoo layer's. The checks that need the world are made here.
    """

    def __init__(self, config: EnvConfig | None = None, **kwargs: Any) -> None:
        if config is None:
            config = EnvConfig(**kwargs)
        elif kwargs:
            raise ValueError("give either an EnvConfig or keyword arguments, not both")
        self.config = c = config
        self.n_robots = c.n_robots
        self.faults = c.faults
        self.trajectory_name = c.trajectory
        self.fast = c.fast
        self.noise = c.noise
        self.profile = get_noise_profile(c.noise)
        self.observe_estimates = c.observe_estimates
        self.use_estimators = c.estimators
        self.world = World(self.n_robots)
        self.cargo_draw = CargoDraw.from_args(
            self.world, c.cargo_mass_kg, c.cargo_com_m, c.cargo_inertia
        )
        self.control_hz = c.control_hz
        self.dt_s = 1.0 / c.control_hz
        self.frame_skip = self._check_frame_skip(c.frame_skip)
        # The control period is exact: the physics step is the period over frame_skip.
        self.world.model.opt.timestep = self.dt_s / self.frame_skip
        # The world with every robot holding: each episode starts in it (a release rebuilds the
        # world without the robot, see _release), and state() keeps its layout.
        self._full_world = self.world
        self._full_data = mujoco.MjData(self.world.model)
        # Each fault with the control steps [first, end) it is active at.
        self._fault_windows = [(f, *f.steps(self.dt_s)) for f in self.faults]
        self.release_steps = parse_release_at(c.release_at, self.n_robots, self.dt_s)
        self.comm_args = (c.comm_latency, c.comm_drop, c.comm_noise)
        CommChannel(self.n_robots, *self.comm_args, self.dt_s, np.random.default_rng(0))
        self.weights = c.weights
        self._weights = np.array([self.weights[t] for t in REWARD_TERMS])
        self.shared_reward = c.shared_reward
        self.estimator_kwargs = {
            **estimator_noise_kwargs(self.profile),
            "peer_noise_std": c.comm_noise,
            **(c.estimator_kwargs or {}),
        }
        # A named figure-eight, "excite" (the team's design) or a design file (agents.excitation).
        self.trajectory = make_trajectory(
            c.trajectory, self.n_robots, self.fast, self.world, self.estimator_kwargs
        )
        self.robots = [self.world.robot_model(i) for i in range(self.n_robots)]
        self.thrust_limits = np.array([r.thrust_limit for r in self.robots])
        self.joint_ranges = np.array([r.joint_range for r in self.robots])
        self._joint_low, self._joint_high = self.joint_ranges[..., 0], self.joint_ranges[..., 1]
        self._bind_world(self._full_world, self._full_data)
        self._init_layouts()
        if self.use_estimators:  # fail early on bad estimator settings
            self._make_estimators()
        self.step_count = 0
        self._ready = False
        self._ref_cache: list | None = None

    def _check_frame_skip(self, frame_skip: int | None) -> int:
        """Physics steps per control step: None gives the MJCF's timestep (or less)."""
        mjcf_timestep = float(self.world.model.opt.timestep)
        if frame_skip is None:
            frame_skip = max(1, math.ceil(self.dt_s / mjcf_timestep - 1e-9))
        if frame_skip < 1 or self.dt_s / frame_skip > MAX_TIMESTEP_S:
            raise ValueError(
                f"frame_skip must be a positive integer with control period / frame_skip <= "
                f"{MAX_TIMESTEP_S} s, got {frame_skip} at {self.control_hz} Hz"
            )
        return int(frame_skip)

    def _init_layouts(self) -> None:
        """Handrail poses, the observation layout, the peer slots and the state's size."""
        # Robot i's handrail (its grasp site on the cargo) in the cargo frame: known geometry.
        self.handrail_pose = [
            (quat_to_mat(self.model.site_quat[site]), self.model.site_pos[site].copy())
            for site in self.world.handrail_sites
        ]
        self.obs_layout = observation_layout(self.n_robots, self.observe_estimates)
        self._observations = ObservationBuilder(self.obs_layout, self.robots, self.handrail_pose)
        # Per robot: the peer in each of its peer slots (increasing index, skipping itself).
        self._peer_slots = [
            [j for j in range(self.n_robots) if j != i] for i in range(self.n_robots)
        ]
        self.obs_dim = self.obs_layout["all"].stop
        full = self._full_world.model
        self.state_dim = 1 + full.nq + full.nv + 13 * (full.nbody - 1)
        self.state_dim += 10 + 21 + 2 * self.n_robots + self.n_robots

    def _make_estimators(self) -> list[CargoEstimator]:
        return make_estimators(
            self.robots, self.dt_s, self.estimator_kwargs, self.world.relative_grasp
        )

    def _bind_world(self, world: World, data: mujoco.MjData) -> None:
        """Simulate ``world`` (with its state in ``data``): the robots it holds act, and the
        indices into its model are refreshed."""
        self.world, self.model, self.data = world, world.model, data
        self._bind_views()
        self.holding = world.holding
        self._acting_mask = np.zeros(self.n_robots, dtype=np.bool_)
        self._acting_mask[list(self.holding)] = True
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
        self.cargo = self.cargo_draw.sample(cargo_rng, self.world)
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
        self.estimation = TeamEstimation(
            self.n_robots, self.estimators, self.true_params_grasp, self.dt_s
        )
        self.navigator = BaseNavigator(self.robots, self.dt_s, self.profile)
        self.arm_targets = np.tile(np.asarray(ARM_DEPLOYED_RAD), (self.n_robots, 1))
        self.arm_rates = np.zeros((self.n_robots, 2))  # the servo targets' rate, rad/s
        self.peer_msgs = self.estimation.peer_msgs  # per receiver: sender -> latest message
        self.step_count = 0
        self._ready = True

        readings = self._read_at_rest()
        self._update_estimators(readings, np.zeros((self.n_robots, 6)), 0)
        self.navigator.reset(readings)
        self.readings = readings
        self._refresh_estimates()
        self._log_std_sum = self._estimate_log_std_sums()
        everyone = self.holding
        obs = self._get_obs(self._acting_mask)
        zero_terms = {t: [0.0] * self.n_robots for t in REWARD_TERMS}
        none = np.zeros(self.n_robots, dtype=int)
        infos = self._get_infos(zero_terms, none, none, None, everyone, ())
        return obs, infos

    def _read_at_rest(self) -> SensorReadings:
        """The first reading: the robots rest for one period before the episode starts, so the
        IMU reads its noise only, and a localization fix and the encoders come with it."""
        t0 = float(self.data.time)
        self.sensors.begin_period(self.data)
        self.data.time = t0 + self.dt_s
        try:
            readings = self.sensors.read_arrays(self.data, 0)
        finally:
            self.data.time = t0
        return readings  # every robot holds at reset: one row per robot, in index order

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
        acting_mask = self._acting_mask
        bad = first_non_finite(actions, acting_mask)
        if bad >= 0:
            raise ValueError(f"actions of robot {bad} are not all finite")
        previous_targets = self.arm_targets
        clipped, n_clipped, effort, commands, self.arm_targets = scale_actions(
            actions, acting_mask, self.thrust_limits, self.arm_targets, self._joint_low,
            self._joint_high, ARM_SPEED_RADPS * self.dt_s, ARM_DEPLOYED, ARM_OFFSET_RAD,
        )  # fmt: skip
        self.arm_rates = (self.arm_targets - previous_targets) / self.dt_s
        saturated = np.where(acting_mask, thrust_saturation(actions, clipped), 0.0)
        self.step_count += 1
        k = self.step_count

        self._apply_commands(commands)
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        self._forward_kinematics()
        finite = self._physics_finite()
        readings = self._read_sensors(k)
        self._update_estimators(readings, commands, k)
        self.navigator.update(readings, self._acting_mask)
        self.readings = readings

        robot_contacts, cargo_contacts = self._wall_contacts()
        # A release due with a non-finite state does not happen: the episode ends (non_finite).
        released = ()
        if self.release_steps and finite:
            released = tuple(i for i in acting if self.release_steps.get(i) == k)
        if released:
            self._release(released)
        obs = self._get_obs(acting_mask)
        if not all_finite(obs):
            finite = False
            obs = np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0)
        reason = None
        if not finite:
            reason = "non_finite"
        elif robot_contacts.sum() + cargo_contacts > 0:
            reason = "wall_contact"
        terms, rewards = self._get_rewards(
            -effort, robot_contacts, cargo_contacts, finite, acting_mask
        )
        infos = self._get_infos(
            terms, n_clipped, robot_contacts + cargo_contacts, reason, acting, released, saturated
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
                self.estimation.forget(i, j)
            if self.estimators:
                self.estimators[i].set_peers([j for j in self.holding if j != i])

    # ------------------------------------------------------------------ one step, in order
    def _apply_commands(self, commands: np.ndarray) -> None:
        """Write d.ctrl of the robots holding the cargo: the thrust ``commands`` (n_robots, 6)
        with actuation noise and the servo targets; start the period."""
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

    def _forward_kinematics(self) -> None:
        """The stages of ``mj_forward`` that the step reads after ``mj_step``: positions,
        contacts and position sensors, then velocities. The acceleration stage (qacc,
        constraint forces, acceleration sensors) is left as ``mj_step`` computed it, for the
        state before its last integration: nothing here reads it, and the next ``mj_step``
        recomputes it from qpos, qvel, ctrl and the solver's warm start."""
        mujoco.mj_fwdPosition(self.model, self.data)
        mujoco.mj_sensorPos(self.model, self.data)
        mujoco.mj_fwdVelocity(self.model, self.data)

    def _physics_finite(self) -> bool:
        unstable = self._warnings[_UNSTABLE].any()
        return bool(
            all_finite(self._qpos) and all_finite(self._qvel) and not unstable
        )

    def _read_sensors(self, k: int) -> SensorReadings:
        """Every robot's readings, one row per robot index (nothing valid in the rows of robots
        that have let go), with the faults of step ``k`` applied (after the sensor noise draws,
        so a run with faults draws the same noise as one without)."""
        readings = self.sensors.read_arrays(self.data, k)
        if not isinstance(self._rows, slice):  # some robots let go: their rows stay empty
            readings = readings.in_rows(self._rows, self.n_robots)
        for fault in self._active_faults("imu_dropout", k):
            i = fault.robot
            if not readings.has_imu[i]:
                continue  # let go, or two overlapping dropouts
            if fault.prob < 1.0 and self.fault_rng.random() >= fault.prob:
                continue
            readings.has_imu[i] = False
            self.fault_counts["imu_frames_missing"][i] += 1
        for fault in self._active_faults("localization_outage", k):
            i = fault.robot
            if readings.has_fix[i]:
                readings.has_fix[i] = False
                self.fault_counts["fixes_missing"][i] += 1
        return readings

    def _active_faults(self, kind: str, k: int) -> list[Fault]:
        """The faults of ``kind`` active at control step ``k``."""
        if not self._fault_windows:
            return []
        return [f for f, first, end in self._fault_windows if f.kind == kind and first <= k < end]

    def _fault_infos(self) -> list[dict[str, Any]]:
        """Every robot's injected-fault counters (episode totals) and the kinds active now."""
        if not self._fault_windows:  # none injected: every counter stays 0
            return [{**NO_FAULT_COUNTS, "active": []} for _ in range(self.n_robots)]
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

    def _update_estimators(self, readings: SensorReadings, commands: np.ndarray, k: int) -> None:
        """The team's estimation of step ``k`` (``TeamEstimation.step``); the estimates are
        gathered again when one changed."""
        if self.estimators and self.estimation.step(
            readings, commands, k, self.holding, self.arm_rates, self.channel
        ):
            self._refresh_estimates()

    def _refresh_estimates(self) -> None:
        if not self.estimators:
            self.est_mean, self.est_std, self.est_errors = [], [], []
            self._estimates = np.zeros((self.n_robots, 0))
            return
        self.est_mean, self.est_std, self.est_errors = self.estimation.refresh()
        # The observation's estimate blocks (N, 20), or none (N, 0).
        observed = (self.est_mean, self.est_std) if self.observe_estimates else ()
        self._estimates = np.concatenate((*observed, np.zeros((self.n_robots, 0))), axis=1)

    def _estimate_log_std_sums(self) -> np.ndarray:
        """Sum of the log standard deviations of each robot's estimate (as of the last refresh)."""
        if not self.estimators:
            return np.zeros(self.n_robots)
        return self.estimation.log_std_sums

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
            cache[2] = self.trajectory(cache[0])
        return cache[2]

    def _reference_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference at the current time as arrays: rotation (3, 3); position, velocity,
        acceleration, angular velocity and angular acceleration (5, 3), world; pan angle and
        rate (2,)."""
        return self._reference_cache()[1]

    def _reference_cache(self) -> list:
        """[time, the reference's arrays, its Reference once asked for]."""
        t = float(self.data.time)
        if self._ref_cache is None or self._ref_cache[0] != t:
            self._ref_cache = [t, self.trajectory.arrays(t), None]
        return self._ref_cache

    def _get_obs(self, acting: np.ndarray) -> np.ndarray:
        """Observations of the ``acting`` robots (bool (N,); the others' rows zeros), from the
        layout (``envs.observations``). A peer that has let go of the cargo has its slot zeroed: its
        messages are forgotten (``_release``)."""
        ref_rot, ref_vecs, ref_pan = self._reference_arrays()
        nav = self.navigator
        peer_wrench, peer_age, peer_valid, peer_arm = self._peer_slot_values(acting)
        return self._observations.build(
            acting, nav.rot, nav.base_pos, nav.base_vel, nav.w_base, self.readings.joint_pos_rad,
            self.arm_targets, ref_rot, ref_vecs, ref_pan, peer_wrench, peer_age, peer_valid,
            self._estimates, self.arm_rates, peer_arm,
        )  # fmt: skip

    def _peer_slot_values(self, acting: np.ndarray) -> tuple[np.ndarray, ...]:
        """Each robot's peer slots (``TeamEstimation.peer_slot_values``)."""
        return self.estimation.peer_slot_values(acting, self.step_count)

    # ------------------------------------------------------------------ rewards, infos
    def tracking_error(self) -> tuple[float, float]:
        """True cargo frame position error (m) and rotation angle error (rad)."""
        b = self.world.cargo_body
        ref_rot, ref_vecs, _ = self._reference_arrays()
        return tracking_errors(self._xpos[b], self._xmat[b].reshape(3, 3), ref_vecs[0], ref_rot)

    def _get_rewards(
        self,
        effort: np.ndarray,
        robot_contacts: np.ndarray,
        cargo_contacts: int,
        finite: bool,
        acting: np.ndarray,
    ) -> tuple[dict[str, list[float]], np.ndarray]:
        """Every reward term per robot, weighted and mixed (team vs individual), and their sum
        per robot; ``effort`` is -|a|^2 per robot; the team of this step is the ``acting``
        robots (bool (N,); the others' rows zeros)."""
        if finite:
            pos_err, angle_err = self.tracking_error()
            track = -(pos_err + ROTATION_WEIGHT_M_PER_RAD * angle_err)
        else:
            track = 0.0
        info = np.zeros(self.n_robots)  # without estimators: no information gained
        if self.estimators:
            log_std = self._estimate_log_std_sums()
            gain = self._log_std_sum - log_std
            self._log_std_sum = log_std
            if np.isfinite(gain).all():
                info = gain
        return reward_terms(
            track, effort, info, robot_contacts, cargo_contacts, acting, self._weights,
            self.shared_reward,
        )  # fmt: skip

    def _get_infos(
        self,
        terms: dict[str, list[float]],
        n_clipped: np.ndarray,
        wall_contacts: np.ndarray,
        reason: str | None,
        robots: tuple[int, ...],
        released: tuple[int, ...],
        saturated: np.ndarray | None = None,
    ) -> list[dict[str, Any] | None]:
        """Infos of ``robots`` (None for the others); ``released``: those letting go now;
        ``saturated`` (n_robots,): ``thrust_saturation`` of this step (zeros at reset)."""
        infos: list[dict[str, Any] | None] = [None] * self.n_robots
        comm = dict(self.channel.stats)
        rewards = [terms[t] for t in REWARD_TERMS]
        n_clipped, wall_contacts = n_clipped.tolist(), wall_contacts.tolist()
        saturated = [0.0] * self.n_robots if saturated is None else saturated.tolist()
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
                saturated=saturated[i],
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
            mat_to_quat(ref.rot),
            ref.w,
            ref.wd,
            np.array([ref.pan, ref.pan_rate]),
            (self.arm_targets * holding[:, None]).ravel(),
            holding,
        ]
        return np.concatenate(parts).astype(np.float64)
