"""The physics, sensing, estimation and rewards of the cargo transport, with no multi-agent API
(``CargoTransport``); ``AstrobeeCargoEnv`` in ``astrocargo.envs.cargo_transport`` is the
PettingZoo layer on top, and its docstring describes both."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from astrocargo.agents.excitation import make_trajectory
from astrocargo.agents.trajectories import SHAPE_DTYPE, Reference
from astrocargo.envs.actions import (  # noqa: F401 (re-exported)
    ACTION_DIM,
    ARM_DEPLOYED,
    ARM_OFFSET_RAD,
    ARM_SPEED_RADPS,
    command_period,
    first_non_finite,
    thrust_saturation,
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
    FreshEstimators,
    TeamEstimation,
    make_estimators,
)
from astrocargo.envs.faults import FaultSchedule, parse_release_at
from astrocargo.envs.infos import REWARD_KEYS, step_infos  # noqa: F401 (re-exported)
from astrocargo.envs.navigation import BaseNavigator
from astrocargo.envs.observations import ObservationBuilder, observation_layout
from astrocargo.envs.physics import UNSTABLE_WARNINGS, PeriodStepper
from astrocargo.envs.rewards import (  # noqa: F401 (re-exported)
    ROTATION_WEIGHT_M_PER_RAD,
    tracking_errors,
)
from astrocargo.envs.sensors import (
    FreshReadings,
    SensorReadings,
    SensorSuite,
    estimator_noise_kwargs,
    imu_state_into,
)
from astrocargo.envs.sensors import noise_profile as get_noise_profile
from astrocargo.envs.step_kernels import commands as step_commands
from astrocargo.envs.step_kernels import (
    no_peer_slots,
    observe_and_reward,
    sense_and_navigate,
    sense_observe_and_reward,
)
from astrocargo.envs.world import ARM_DEPLOYED_RAD, MAX_TIMESTEP_S, World
from astrocargo.estimator.checks import all_finite
from astrocargo.estimator.geometry import mat_to_quat, quat_to_mat
from astrocargo.estimator.records import as_interned, bound_views, record_of

TERMINATION_REASONS = ("wall_contact", "non_finite", "released")  # "released": one agent
NO_SHAPE = np.zeros(0, dtype=SHAPE_DTYPE)  # observe_and_reward's shapes: the reference is written


@dataclass(slots=True)
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
        self.fault_schedule = FaultSchedule(self.faults, self.dt_s, self.n_robots)
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
        self._init_step_arrays()
        self._fresh_estimators = FreshEstimators(
            self.robots, self.dt_s, self.estimator_kwargs, self.world.relative_grasp
        )
        if self.use_estimators:  # fail early on bad estimator settings
            self._fresh_estimators()
        self.step_count = 0
        self._ready = False
        self._ref_cache: list | None = None
        self._ref_arrays = (np.empty((3, 3)), np.empty((5, 3)), np.empty(2))

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

    def _init_step_arrays(self) -> None:
        """The per-robot arrays every step rewrites in place (what the step hands out is new)."""
        n = self.n_robots
        self._n_clipped, self._effort = np.zeros(n, dtype=np.int64), np.zeros(n)
        self._saturation, self._no_info = np.zeros(n), np.zeros(n)
        self._no_contacts = np.zeros(n, dtype=int)  # per robot, while no geom touches the module
        self._mixed = np.zeros((len(REWARD_TERMS), n))  # the weighted, mixed terms
        # Without estimators: the same readings (and their record) every step; with them, new
        # ones (an estimator may keep a reading).
        self._readings = SensorReadings.empty_record(n)
        self._fresh_readings = FreshReadings(n)
        self._no_peers = no_peer_slots(n)  # peer slots without estimators
        self._thrust = np.empty((n, 6))  # the thrust commands of a step without estimators

    def _bind_world(self, world: World, data: mujoco.MjData) -> None:
        """Simulate ``world`` (with its state in ``data``): the robots it holds act, and the
        indices into its model are refreshed."""
        self.world, self.model, self.data = world, world.model, data
        self._bind_views()
        self.holding = world.holding
        self._acting_mask = np.zeros(self.n_robots, dtype=np.bool_)
        self._acting_mask[list(self.holding)] = True
        self._row_index = np.array(self.holding, dtype=np.int64)  # their rows, robot index
        self._unit_scale = np.ones(len(self.holding))
        self._imu_ok, self._fix_ok = np.ones((2, self.n_robots), dtype=np.bool_)
        # The IMUs' velocities (H, 3) and rotations (H, 3, 3) at the start of the period.
        n_world = len(self.holding)
        self._imu_v0, self._imu_r0 = np.zeros((n_world, 3)), np.zeros((n_world, 3, 3))
        self._physics = PeriodStepper(self.model, data, self.frame_skip)
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

    _VIEWS = ("_ctrl", "_xpos", "_xmat", "_sensor_views", "_cargo_pose")

    def _bind_views(self) -> None:
        """Views of the data's arrays used every step (each property access builds a new one)."""
        data = self.data
        self._ctrl, self._xpos, self._xmat = data.ctrl, data.xpos, data.xmat
        self._sensor_views = (
            data.cvel, data.site_xpos, data.site_xmat, data.subtree_com, data.sensordata,
        )  # fmt: skip
        self._cargo_pose = (data.xpos, data.xmat, self.world.cargo_body)

    # A copy (copy.deepcopy, pickle) gets its own MjData: the views are rebound to it, not copied
    # as detached arrays.
    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k not in self._VIEWS}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._bind_views()
        if "_step_record" in state:
            self._step_record = as_interned(self._step_record)  # unpickled: a new dtype object
            self._bind_record_views()
        readings, record = self._readings
        self._readings = readings, as_interned(record)
        readings.view_record(self._readings[1])

    # The step record's fields that are views of attributes (written in place from Python); the
    # others are constants, copied in (``_bind_step_record``).
    _RECORD_VIEWS = {
        "imu_v0": "_imu_v0", "imu_r0": "_imu_r0", "imu_ok": "_imu_ok", "fix_ok": "_fix_ok",
        "acting": "_acting_mask", "arm_targets": "arm_targets", "arm_rates": "arm_rates",
        "n_clipped": "_n_clipped", "effort": "_effort", "saturation": "_saturation",
        "mixed": "_mixed",
    }  # fmt: skip
    _REF_FIELDS = ("ref_rot", "ref_vecs", "ref_pan")  # the reference's arrays (_ref_arrays)

    def _bind_step_record(self) -> None:
        """The arrays of the world's step in one record (``estimator.records``; the fields that
        ``step_kernels`` reads): the sensors' indices and noise, the actuators, the observation
        layout and the reward weights copied in; the IMU states, the faults' masks, the acting
        mask, the arms' targets and rates, the step's effort, clipping, saturation and mixed
        terms and the reference's arrays become views of it, and so do the period stepper's
        saved qpos and qvel (``_bind_record_views``)."""
        s, ob = self.sensors, self._observations
        self._step_record = record_of(
            {
                "unstable": UNSTABLE_WARNINGS, "imu_index": s.imu_index,
                "joint_adr": s.joint_adr, "pos_adr": s.pos_adr, "quat_adr": s.quat_adr,
                "noise_std": s.noise_std, "rows": self._row_index,
                "thrust_limits": self.thrust_limits, "joint_low": self._joint_low,
                "joint_high": self._joint_high, "actuation_std": s.actuation_std,
                "thrust_ctrl": self._thrust_ctrl, "arm_ctrl": self._arm_ctrl,
                "own_starts": ob.own_starts, "peer_starts": ob.peer_starts,
                "estimate_start": np.array([ob.estimate_start]),
                "link_parent": ob.link_parent, "weights": self._weights,
                "shared": np.array([float(self.shared_reward)]),
                "cargo_body": np.array([self.world.cargo_body]),
                "dt_s": np.array([self.dt_s]),  # the control period (the navigators' too)
                "max_move_rad": np.array([ARM_SPEED_RADPS * self.dt_s]),  # the servos' per period
                "saved_qpos": self._physics.saved_qpos, "saved_qvel": self._physics.saved_qvel,
                **{field: getattr(self, name) for field, name in self._RECORD_VIEWS.items()},
                **dict(zip(self._REF_FIELDS, self._ref_arrays, strict=True)),
            }
        )  # fmt: skip
        self._bind_record_views()

    def _bind_record_views(self) -> None:
        views = bound_views(self._step_record)
        for field, name in self._RECORD_VIEWS.items():
            setattr(self, name, views[field])
        # The period stepper's saved state lives in the record (the kernels compare and save it
        # there), carrying what the stepper held (NaN in a copy: its first period in full).
        p = self._physics
        views["saved_qpos"][:], views["saved_qvel"][:] = p.saved_qpos, p.saved_qvel
        p.saved_qpos, p.saved_qvel = views["saved_qpos"], views["saved_qvel"]
        self._ref_arrays = tuple(views[field] for field in self._REF_FIELDS)
        self._ref_cache = None

    # ------------------------------------------------------------------ episode
    def reset(self, rng: np.random.Generator) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """Start an episode; sensor, channel and cargo generators are spawned from ``rng``.
        Returns the observations (n_robots, obs_dim) and infos."""
        sensor_rng, comm_rng, cargo_rng = rng.spawn(3)
        # Spawned only with faults, so that a run without them draws as it always did.
        self.fault_rng = rng.spawn(1)[0] if self.faults else None
        self.cargo = self.cargo_draw.sample(cargo_rng, self.world)
        if self.world is not self._full_world:  # robots let go last episode
            self._bind_world(self._full_world, self._full_data)
        self.released_at_s: dict[int, float] = {}
        self.released_momentum: dict[int, np.ndarray] = {}
        self.world.set_cargo(*self.cargo)
        self.world.reset_data(self.data)
        self.true_params = self.world.cargo_params()
        in_grasp_frame = self.world.cargo_params_in_grasp_frame
        self.true_params_grasp = np.array(
            [in_grasp_frame(i, self.true_params) for i in range(self.n_robots)]
        )  # (n_robots, 10), row i in robot i's grasp frame
        self.arm_targets = np.tile(np.asarray(ARM_DEPLOYED_RAD), (self.n_robots, 1))
        self.arm_rates = np.zeros((self.n_robots, 2))  # the servo targets' rate, rad/s
        self.sensors = SensorSuite(self.world, self.profile, sensor_rng)
        self._bind_step_record()
        self._kinematics_done()
        self.channel = CommChannel(
            self.n_robots, *self.comm_args, self.dt_s, comm_rng, fault_rng=self.fault_rng
        )
        self.fault_schedule.reset(self.fault_rng, self.channel)
        self.estimators = self._fresh_estimators() if self.use_estimators else []
        self.estimation = TeamEstimation(
            self.n_robots, self.estimators, self.true_params_grasp, self.dt_s
        )
        self.navigator = BaseNavigator(self.robots, self.dt_s, self.profile)
        self.peer_msgs = self.estimation.peer_msgs  # per receiver: sender -> latest message
        self.step_count = 0
        self._ready = True

        readings = self._read_at_rest()
        self._update_estimators(readings, np.zeros((self.n_robots, 6)), 0)
        self.navigator.reset(readings)
        self.readings = readings
        self._refresh_estimates()
        self._log_std_sum, self._gain_due = self._estimate_log_std_sums(), False
        obs = self._get_obs(self._acting_mask)
        zero_terms = np.zeros((len(REWARD_TERMS), self.n_robots))
        none = np.zeros(self.n_robots, dtype=int)
        infos = step_infos(self, zero_terms, none, none, None, self.holding, ())
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
        return self.step_checked(self.checked_actions(actions))

    def checked_actions(self, actions: np.ndarray) -> np.ndarray:
        """``actions`` as float64 (n_robots, 8); ``ValueError`` on another shape or on a
        non-finite entry in the row of a robot holding the cargo."""
        actions = np.asarray(actions, dtype=float)
        if actions.shape != (self.n_robots, ACTION_DIM):
            raise ValueError(
                f"actions must have shape {(self.n_robots, ACTION_DIM)}, got {actions.shape}"
            )
        bad = first_non_finite(actions, self._acting_mask)
        if bad >= 0:
            raise ValueError(f"actions of robot {bad} are not all finite")
        return actions

    def step_checked(self, actions: np.ndarray) -> StepResult:
        """``step`` of actions already checked: float64 (n_robots, 8), every acting row finite
        (what the PettingZoo layer hands over after its own checks)."""
        if not self._ready:
            raise RuntimeError("call reset() before step(), and again after the episode ended")
        acting = self.holding  # the robots of this step, those letting go at its end included
        self.step_count = k = self.step_count + 1
        fix = k % self.profile.localization_every == 0
        normals = self.sensors.draw_step(fix)
        self._fault_masks(k, fix)
        commands = self._apply_commands(actions, normals)
        self._physics.integrate(self._kinematics_current)
        time_s = float(self.data.time)  # the step's end
        robot_contacts, cargo_contacts, n_contacts = self._wall_contacts()
        obs, rewards = np.empty((self.n_robots, self.obs_dim)), np.empty(self.n_robots)
        contacts = robot_contacts, cargo_contacts
        if self.estimators or self.release_steps:
            finite, released = self._sense_estimate_observe(
                obs, rewards, fix, normals, commands, time_s, contacts
            )
        else:
            finite, released = self._sense_observe(obs, rewards, fix, normals, time_s, contacts), ()
        self._ref_cache = [time_s, self._ref_arrays, None]  # the step's record holds them
        reason = None
        if not finite:
            reason = "non_finite"
        elif n_contacts > 0:
            reason = "wall_contact"
        # Each robot's contacts plus the cargo's (numpy's scalar add alone costs about 1 us).
        contacts = robot_contacts + cargo_contacts if cargo_contacts else robot_contacts
        infos = step_infos(
            self, self._mixed, self._n_clipped, contacts, reason, acting, released, self._saturation
        )
        if reason is not None or not self.holding:
            self._ready = False
        return StepResult(obs, rewards, reason is not None, reason, infos, released)

    def _sense_estimate_observe(
        self, obs: np.ndarray, rewards: np.ndarray, fix: bool, normals: np.ndarray,
        commands: np.ndarray, time_s: float, contacts: tuple[np.ndarray, int],
    ) -> tuple[bool, tuple[int, ...]]:  # fmt: skip
        """After the physics, at the step's end ``time_s`` (s): the readings and navigation, the
        estimators of the thrust ``commands``, the releases due (when the state is finite), then
        the observations and rewards of the robots acting at the step's start into ``obs`` and
        ``rewards``; ``contacts``: the wall contacts per robot and of the cargo. Returns whether
        the state and observations are finite, and the robots released."""
        acting, acting_mask, k = self.holding, self._acting_mask, self.step_count
        finite, readings, readings_record = self._sense_and_navigate(fix, normals, time_s)
        if self.estimators:
            self._update_estimators(readings, commands, k)
        self.readings = readings
        # A release due with a non-finite state does not happen: the episode ends (non_finite).
        released = ()
        if self.release_steps and finite:
            released = tuple(i for i in acting if self.release_steps.get(i) == k)
        if released:
            self._release(released)
        finite = observe_and_reward(
            obs, rewards, acting_mask, self._step_record, readings_record, self.navigator.filters,
            self._observations.arms, self._xpos, self._xmat,
            self._peer_observations(acting_mask),
            self._estimates, self._info_gain(), *contacts, finite,
            self._reference_shapes(time_s), time_s,
        )  # fmt: skip
        return finite, released

    def _sense_observe(
        self, obs: np.ndarray, rewards: np.ndarray, fix: bool, normals: np.ndarray,
        time_s: float, contacts: tuple[np.ndarray, int],
    ) -> bool:  # fmt: skip
        """``_sense_estimate_observe`` of a step with no estimators and no release due: the
        readings (the same arrays every step), the navigation, the observations and rewards in
        one compiled call (``step_kernels.sense_observe_and_reward``). Returns finite."""
        r, record = self._readings
        r.time_s = time_s
        self.readings = r
        cvel, site_xpos, site_xmat, subtree_com, sensordata = self._sensor_views
        p = self._physics
        return sense_observe_and_reward(
            p.qpos, p.qvel, p.warnings, cvel, site_xpos, site_xmat, subtree_com, sensordata,
            time_s - self._period_start_s, normals, fix, self._step_record, record,
            self.navigator.filters, obs, rewards, self._observations.arms, self._xpos, self._xmat,
            *contacts, self._reference_shapes(time_s), time_s,
        )  # fmt: skip

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
        self.sensors = SensorSuite(world, self.profile, self.sensors.normals)
        self._bind_step_record()
        self._kinematics_done()
        for i in released:
            self.channel.disconnect(i)
        for i in self.holding:
            for j in released:
                self.estimation.forget(i, j)
            if self.estimators:
                self.estimators[i].set_peers([j for j in self.holding if j != i])

    # ------------------------------------------------------------------ one step, in order
    def _apply_commands(self, actions: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Scale the ``actions`` (``command_period``) and write d.ctrl of the robots holding the
        cargo: the thrust commands with actuation noise (the first 6 H of the step's standard
        ``normals``, ``SensorSuite.draw_step``) and the servo targets; start the period. Returns the
        thrust commands (N, 6)."""
        p = self._physics
        # The IMU states that started the period: kept from the last reading while qpos and
        # qvel are as the last step (or reset) left them (``PeriodStepper.unchanged``). New
        # commands while estimators run (they may keep them), else the same array.
        commands = np.empty((self.n_robots, 6)) if self.estimators else self._thrust
        self._kinematics_current = step_commands(
            actions, normals,
            self.fault_schedule.thrust_scale(self.step_count, self.holding, self._unit_scale),
            self._ctrl, self._step_record, p.qpos, p.qvel, commands,
        )  # fmt: skip
        if not self._kinematics_current:
            self._imu_period_start()
        self._period_start_s = float(self.data.time)
        return commands

    def _imu_period_start(self) -> None:
        """The IMUs' velocities and rotations now, as the start of a period."""
        cvel, site_xpos, site_xmat, subtree_com, _ = self._sensor_views
        imu_state_into(
            self._imu_v0, self._imu_r0, cvel, site_xpos, site_xmat, subtree_com,
            self.sensors.imu_index,
        )  # fmt: skip

    def _kinematics_done(self) -> None:
        """The data's position and velocity stages are those of its qpos and qvel now (after
        ``mj_forward``): the next step may skip them (``envs.physics``) and start its period
        from the IMU states now."""
        self._physics.forward_done()
        self._imu_period_start()

    def _fault_masks(self, k: int, fix: bool) -> None:
        """The IMU frames and fixes the faults of step ``k`` leave (``_imu_ok``, ``_fix_ok``,
        bool (N,)), drawn before the physics: the faults' generator draws in the same order."""
        if not self.fault_schedule.windows:  # the masks stay all True
            return
        self._imu_ok[:] = self._acting_mask
        np.logical_and(self._acting_mask, fix, out=self._fix_ok)
        self.fault_schedule.apply_to_readings(self._imu_ok, self._fix_ok, k)

    def _sense_and_navigate(
        self, fix: bool, normals: np.ndarray, time_s: float
    ) -> tuple[bool, SensorReadings, np.ndarray]:
        """After the physics, at the period's end ``time_s`` (s): whether the state is finite;
        every robot's readings, one row per robot index (nothing valid in the rows of robots that
        have let go) with the faults' masks and the step's standard ``normals``
        (``SensorSuite.draw_step``); the navigation filters (``step_kernels.sense_and_navigate``).
        Fresh reading arrays while estimators run (they may
        keep a reading), else the same ones every step."""
        r, record = self._fresh_readings() if self.estimators else self._readings
        r.time_s = time_s
        cvel, site_xpos, site_xmat, subtree_com, sensordata = self._sensor_views
        p = self._physics
        finite = sense_and_navigate(
            p.qpos, p.qvel, p.warnings, cvel, site_xpos, site_xmat, subtree_com, sensordata,
            time_s - self._period_start_s, normals, fix, self._step_record, record,
            self.navigator.filters,
        )  # fmt: skip
        return finite, r, record

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
        self._gain_due = True  # the log std sums are new (``_info_gain``)
        # The observation's estimate blocks (N, 20), or none (N, 0).
        observed = (self.est_mean, self.est_std) if self.observe_estimates else ()
        self._estimates = np.concatenate((*observed, np.zeros((self.n_robots, 0))), axis=1)

    def _estimate_log_std_sums(self) -> np.ndarray:
        """Sum of the log standard deviations of each robot's estimate (as of the last refresh)."""
        if not self.estimators:
            return np.zeros(self.n_robots)
        return self.estimation.log_std_sums

    def _wall_contacts(self) -> tuple[np.ndarray, int, int]:
        """Contacts with the module per robot, those of the cargo, and all of them."""
        ncon = self.data.ncon
        if ncon == 0:
            return self._no_contacts, 0, 0
        per_robot = np.zeros(self.n_robots, dtype=int)
        geoms = self.data.contact.geom[:ncon]
        wall = self._wall_geom[geoms]
        owner = self._geom_owner[geoms]
        # The module is static: a wall contact is one with exactly one wall geom.
        hit = wall[:, 0] ^ wall[:, 1]
        other = np.where(wall[:, 0], owner[:, 1], owner[:, 0])[hit]
        per_robot += np.bincount(other[other < self.n_robots], minlength=self.n_robots)
        cargo = int(np.sum(other == self.n_robots))
        return per_robot, cargo, int(per_robot.sum()) + cargo

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
            # The same arrays every time (``_reference_arrays``' callers keep none of them).
            self.trajectory.arrays_into(t, *self._ref_arrays)
            self._ref_cache = [t, self._ref_arrays, None]
        return self._ref_cache

    def _reference_shapes(self, time_s: float) -> np.ndarray:
        """The reference at the step's end ``time_s`` for ``observe_and_reward``: the analytic
        trajectory's shape record, which the kernel evaluates into the step's record; another
        trajectory's arrays are written there now, and the shape is empty."""
        shapes = getattr(self.trajectory, "shape_record", None)
        if shapes is None:
            self.trajectory.arrays_into(time_s, *self._ref_arrays)
            return NO_SHAPE
        return shapes

    def _get_obs(self, acting: np.ndarray) -> np.ndarray:
        """Observations of the ``acting`` robots (bool (N,); the others' rows zeros), from the
        layout (``envs.observations``)."""
        peers = self._peer_observations(acting)
        return self._observations.build(
            acting, self.navigator.filters, self.readings.joint_pos_rad, self.arm_targets,
            *self._reference_arrays(), *peers[:3], self._estimates, self.arm_rates, peers[3],
        )  # fmt: skip

    def _peer_observations(self, acting: np.ndarray) -> tuple[np.ndarray, ...]:
        """The peer slots' (wrench, age, valid, arm) for the observations (zeros without
        estimators). A peer that has let go of the cargo has its slot zeroed: its messages are
        forgotten (``_release``)."""
        return self._peer_slot_values(acting) if self.estimators else self._no_peers

    def _peer_slot_values(self, acting: np.ndarray) -> tuple[np.ndarray, ...]:
        """Each robot's peer slots (``TeamEstimation.peer_slot_values``)."""
        return self.estimation.peer_slot_values(acting, self.step_count)

    # ------------------------------------------------------------------ rewards, infos
    def tracking_error(self) -> tuple[float, float]:
        """True cargo frame position error (m) and rotation angle error (rad)."""
        b = self.world.cargo_body
        ref_rot, ref_vecs, _ = self._reference_arrays()
        return tracking_errors(self._xpos[b], self._xmat[b].reshape(3, 3), ref_vecs[0], ref_rot)

    def _info_gain(self) -> np.ndarray:
        """The info term per robot: this step's decrease of each estimate's sum of log standard
        deviations (zeros without estimators, or when it is not finite). Without a refresh since
        the last step the sums are those of the last step: x - x, zeros (``_no_info``)."""
        if not self.estimators or not self._gain_due:
            return self._no_info
        self._gain_due = False
        log_std = self._estimate_log_std_sums()
        gain = self._log_std_sum - log_std
        self._log_std_sum = log_std
        return gain if all_finite(gain) else np.zeros(self.n_robots)

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
