"""One robot's real-time estimator of the cargo's inertial parameters.

Each robot runs one ``CargoEstimator``. Per control step it takes only what the robot itself has:
its IMU, its arm encoders, its localization fixes (at a lower rate) and its own propulsion command,
plus the messages of the other robots. It

1. pre-filters its raw signals with a fast state-variable filter (``preprocess``, cutoff
   ``kinematics_cutoff_hz``, 1 Hz), which gives the filtered motion the noise model linearises
   the balance at;
2. forms, every control step, the wrench balance of that instant in its grasp frame G (fixed to
   the cargo; moments about the grasp point) in momentum form (``momentum``): Z = d/dt P + Q,
   with P and Q (thrust, the momentum of its own links and their remainder, the cargo
   regressor's momentum form, linear in pi) products of the readings through a fast rate filter
   (``rate_cutoff_hz``, 8 Hz), so that no angular or joint acceleration enters; low-passes the
   samples at ``kinematics_cutoff_hz`` and, every ``regressor_every`` steps, with one slow filter
   (cutoff ``cutoff_hz``), and reads the balance out of that filter's value and derivative,
   H[Z] = H'[P] + H[Q]. Every product is taken before the linear filters, so the filtered
   quantities satisfy the balance exactly (H[thrust] = H[links] + H[Y] pi + sum_j T_ij H[W_j],
   T_ij constant for a rigid cargo) whatever the motion's harmonics. (Products of pre-filtered
   signals, the acceleration form ``rne.balance_in_grasp_frame``, left 1.5 / 6.5 % principal
   moment errors under arm motion at the servos' rate limit; products of the raw signals
   filtered afterwards, ~10 mN residuals under the tumbling trajectory.) The slow filter is
   what removes the noise of the differentiated encoders;
3. at each update instant (every ``update_every`` control steps) publishes the filtered wrench it
   applies to the cargo, H[thrust] - H[links], as a ``WrenchMessage`` (in its grasp frame and in
   world axes), with its grasp pose;
4. keeps a short history of its own instants and, once it holds every peer's message of the
   same instant, updates its UKF with the wrench balance of that instant (``rne``):
       thrust_G = links_G + Y pi - sum_j T_Gi<-Gj W_j;
   a late message waits, an instant still incomplete after ``history_s`` is skipped and counted.

Peers' wrenches arrive in the sender's grasp frame G_j. Since the grasp is rigid, the transform
G_i <- G_j is constant (which is why the balance is written in G: in the base frame the peers'
term would be a product of two filtered signals, not the filtered product); each robot
estimates it by averaging, over the instants at which both
robots had a localization fix, the relative pose of the two grasp frames (their attitude errors
cancel in the wrench itself, which never passes through world axes). The unknown parameters pi are
the cargo's standard parameters in this robot's grasp frame G_i (see ``inertia``).

Bad or missing input, and what is counted (``counters``):

- wrongly shaped readings raise ``ValueError``;
- a non-finite reading (``bad_readings``) or a missing IMU frame (``accel_imu`` and ``gyro_imu``
  None: ``missing_imu``) is not fed to the filters: the previous sample of that signal is held,
  and the update instants within the filters' memory of it (``taint_steps`` control steps, about
  4.9 s at the defaults) are skipped (``skipped_bad_reading``). The messages of those instants
  are published flagged ``tainted``, and a peer skips its instants that hold one
  (``skipped_peer_tainted``): their wrench was built from held data;
- an instant for which a peer's message has not arrived within ``history_s`` is skipped
  (``skipped_missing``); a message that arrives after that is dropped and counted
  (``stale_messages``);
- an instant whose innovation is inconsistent with its covariance (NIS above the chi-square gate)
  is rejected (``gated``). Such an inconsistency (a weakened thruster, whose wrench the robot
  does not know, or a peer's) enters the filtered balance gradually, over the filters' memory
  (``rollback_steps``, 1.2 s at the defaults), and leaves it as gradually: so a gated instant
  also undoes the updates of the instants within that memory before it (``rolled_back``: the
  state returns to the one before them, its covariance grown by the random walk, if any, of
  the skipped predictions) and skips the instants up to ``taint_steps`` after it
  (``skipped_after_gate``).
  Without this, the instants at the start and the end of a fault, inconsistent but still inside
  the gate, biased the estimate (measured when it was added, two robots, nominal noise: one
  thruster at half its command from 20 to 25 s left 3.6 % mass and 3.6 cm centre-of-mass error
  at 40 s; with it 1.6 % and 1.4 cm; without the fault 1.5 % and 1.3 cm). A fault the gate does
  not see while the estimate is still wide is absorbed as a wrong cargo (see the env's Faults);
- ``fixes`` counts the localization fixes used (between fixes the attitude follows the gyro).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Iterator

import numpy as np

from .arguments import check_arguments, motion_lag_steps, nis_gate
from .deferred_reports import DeferredReports
from .fused_motion import FusedMotion, Reading
from .instant_terms import instant_terms, known_transforms, peer_terms
from .messages import Instant, RelativeGrasp, WrenchMessage  # noqa: F401 (re-exported)
from .momentum import SIZE as MOMENTUM_SIZE
from .momentum import cargo_regressor_parts
from .noise_model import NoiseModel
from .over_time import UpdateWindow
from .per_step import EstimatorInputs
from .preprocess import Preprocessor, StateVariableFilter
from .prior import (  # noqa: F401 (re-exported)
    DEFAULT_PRIOR_STD,
    DEFAULT_PROCESS_STD_REL,
    default_prior,
    prior_covariance,
)
from .rate_square import rate_square_var
from .rne import Balance, RobotDescription, grasp_pose, wrench_transform
from .ukf import InertialParamUKF

# A pure function of four numbers that steps a filter's impulse response: one evaluation per
# set-up, not one per estimator and reset.
_cached_rate_square_var = functools.lru_cache(maxsize=16)(rate_square_var)
_NO_MESSAGES: dict = {}  # the peers' messages of a stamp none has arrived for (never written)


class CargoEstimator(EstimatorInputs):
    """Constrained UKF on the cargo's inertial parameters for robot ``index``.

    Args:
        robot: the robot's known model (``World.robot_model``).
        index: this robot's id; ``peers``: the ids of the other robots holding the cargo.
        dt_s: control period; ``update_every``: control steps between update instants.
        prior_params: prior mean pi (10,) in this robot's grasp frame (``default_prior``).
        prior_std: (mass kg, centre of mass m, moments kg m^2, products kg m^2) standard
            deviations of the prior (`prior_covariance`); ``process_std_rel``: random walk of the
            parameters per update, as a fraction of the prior's standard deviations (0 by
            default: a rigid cargo's parameters are constant).
        force_std_n, torque_std_nm: the floors, the balance's model error (what remains of the
            filtered balance with no noise in it), rms per update (``noise_model``).
        actuation_noise: (force_abs_n, force_rel, torque_abs_nm, torque_rel): the robot's known
            propulsion accuracy, white per control step: std = abs + rel * |command| per axis;
            the peers' is sent with their messages.
        cutoff_hz: the slow filter of the wrench balance; ``kinematics_cutoff_hz``: the
            pre-filter of the raw signals and of the momentum form's samples;
            ``rate_cutoff_hz``: the momentum form's rate filter (its derivative gives the joint
            rates; None: 8 Hz, or a quarter of the control rate when that is lower; a 1 Hz one
            distorted the products, raw differences of the encoders squared their noise into a
            bias of the regressor, see ``momentum``); ``regressor_every``: control steps
            between balance evaluations (``update_every`` must be a multiple; 2, i.e. 31 Hz:
            the doubly differentiated encoder noise leaves the 1 Hz pre-filter falling only as
            1/f, and at 5 its aliases biased the 90 s nominal tumble to 4.7 % mass error, NEES 50);
            ``warmup_s``: no update before.
        history_s: how long an instant waits for its peers' messages before it is skipped.
        gate_prob: chi-square probability of the normalised innovation gate (None: no gating).
        sensor_noise: (accel_std m/s^2, gyro_std rad/s, encoder_std rad), white per control
            step: the robot's known sensor specs. They enter the measurement (errors in
            variables, ``motion_fusion``), and instants whose excitation does not stand above
            them are not used (``min_excitation_snr``).
        min_excitation_snr: skip an instant unless its filtered linear or angular acceleration
            exceeds this many standard deviations of its noise (counted as skipped_low_excitation).
        peer_noise_std: (force N, moment N m) of the channel's additive noise on peers' wrenches.
        localization_noise: (position m, attitude rad) of one fix; peers are used once
            ``min_relative_fixes`` simultaneous fixes average their relative grasp pose.
        relative_grasps: known pose (rotation, position) of each peer's grasp frame in this
            robot's grasp frame, {peer: (rot, pos)}: the team's grasp plan (which handrails of
            the cargo they hold) is geometry, not inertia. Without it the pose is estimated from
            localization fixes; a fix-averaged pose is biased early on and that bias stays in the
            updates made with it (measured: 9 mm of CoM error on a 90 s nominal run).
        record: keep every accepted update's (z, A, b, R) in ``log`` for the batch baselines.
        motion_fusion: how the sensors' noise on the motion enters the measurement
            (``NoiseModel.motion_noise``): "none" scalar blocks at the current estimate; "own"
            its full structure through the exact filter chain, this robot's and the peers';
            "team" (default) that, conditioned on the peers' grasp-acceleration mismatch (zero
            in truth for a rigid cargo).
        mismatch_model_std: m/s^2 per axis, rms per update of the mismatch's model error (what it
            holds with perfect sensors), weighted like the floors (``noise_model``).
        over_time_window: 0, each update on its own, the IMU's channels at the lag-weighted
            covariance (``noise_model``); L > 0, each update conditioned on the last L used
            updates (``over_time``: the IMU's noise weighed with its covariance over time, its
            channels at their per-update covariance; the peers must run it too).
        bias_compensation, encoders_over_time: the reported estimate and covariance deferred
            from the filter's (``deferred_reports``; window 0 only). The compensation is off by
            default; ``encoders_over_time`` None (default) reports the covariance with the
            encoders' noise correlated over updates (``encoder_covariance``) wherever that holds
            (window 0, no random walk), True demands it, False reports the filter's P.
        motion_lag_s: 0 (default), the readings as they come; > 0, the accelerometer fused
            with the localization fixes by a fixed-lag smoother of this lag (s, rounded to
            control steps), the pipeline fed every reading ``motion_lag_s`` late
            (``fused_motion``: the estimates and messages are that late; every robot of the
            team must run the same lag; ``flush`` at the end of a flight); its noise model
            follows the smoother's error spectrum. ``localization_every``: control steps
            between fixes (the spectrum's schedule; used only with a lag).
    """

    def __init__(
        self,
        robot: RobotDescription,
        index: int,
        peers: list[int] | tuple[int, ...],
        dt_s: float,
        prior_params: np.ndarray | None = None,
        *,
        update_every: int = 10,
        force_std_n: float = 2.5e-6,
        torque_std_nm: float = 6.6e-7,
        actuation_noise: tuple[float, float, float, float] = (5e-3, 0.02, 5e-4, 0.02),
        prior_std: tuple[float, float, float, float] = DEFAULT_PRIOR_STD,
        process_std_rel: float = DEFAULT_PROCESS_STD_REL,
        cutoff_hz: float = 0.25,
        kinematics_cutoff_hz: float = 1.0,
        regressor_every: int = 2,
        warmup_s: float = 4.0,
        history_s: float = 2.0,
        gate_prob: float | None = 0.9999,
        sensor_noise: tuple[float, float, float] = (1e-3, 2e-4, 1e-3),
        min_excitation_snr: float = 5.0,
        peer_noise_std: tuple[float, float] = (0.0, 0.0),
        localization_noise: tuple[float, float] = (5e-3, np.deg2rad(0.2)),
        min_relative_fixes: int = 10,
        relative_grasps: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
        record: bool = False,
        motion_fusion: str = "team",
        mismatch_model_std: float = 5.3e-7,
        rate_cutoff_hz: float | None = None,
        over_time_window: int = 0,
        bias_compensation: bool = False,
        encoders_over_time: bool | None = None,
        motion_lag_s: float = 0.0,
        localization_every: int = 20,
    ) -> None:
        check_arguments(
            index, peers, update_every, regressor_every, warmup_s, history_s, gate_prob,
            min_excitation_snr, process_std_rel, min_relative_fixes, motion_fusion,
        )  # fmt: skip
        self._init_options(over_time_window, motion_lag_s, dt_s, localization_every)
        self.motion_fusion, self._mismatch_model_std = motion_fusion, float(mismatch_model_std)
        self._init_schedule(
            robot, index, peers, dt_s, update_every, regressor_every, warmup_s, history_s
        )
        self._init_signal_filters(sensor_noise, kinematics_cutoff_hz, cutoff_hz, rate_cutoff_hz)
        self._init_fused_motion(robot, sensor_noise, localization_noise)
        self._init_ukf(prior_params, prior_std, process_std_rel, gate_prob)
        self._init_noise_model(
            force_std_n, torque_std_nm, actuation_noise, sensor_noise, peer_noise_std,
            localization_noise, cutoff_hz, kinematics_cutoff_hz,
        )  # fmt: skip
        self.min_excitation_snr = float(min_excitation_snr)
        self.min_relative_fixes = int(min_relative_fixes)
        self._init_bookkeeping(relative_grasps, record)
        options = (bias_compensation, encoders_over_time, self.over_time_window, self.ukf.Q)
        self._reports = DeferredReports.of(
            self.noise, self.update_every, *options, rollback=self._snapshots.maxlen
        )
        self._init_constants()

    def _init_options(self, over_time_window, motion_lag_s, dt_s, localization_every) -> None:
        """Check and keep the over-time window (updates) and the fused motion's lag (steps)."""
        if over_time_window < 0:
            raise ValueError(f"over_time_window must be >= 0 updates, got {over_time_window}")
        self.over_time_window = int(over_time_window)
        self.motion_lag_steps = motion_lag_steps(motion_lag_s, dt_s, localization_every)
        self._localization_every = int(localization_every)

    def _init_fused_motion(self, robot, sensor_noise, localization_noise) -> None:
        """The fused motion's buffer and smoother (``fused_motion``), with a lag; else None."""
        self._fused = None
        if self.motion_lag_steps:
            self._fused = FusedMotion(
                self.dt_s, self.motion_lag_steps, float(sensor_noise[0]), *localization_noise,
                self._imu_rot, robot.imu_pos,
            )  # fmt: skip

    def _init_schedule(
        self, robot, index, peers, dt_s, update_every, regressor_every, warmup_s, history_s
    ) -> None:
        """Who this robot and its peers are, the control period and the step counts of the
        updates, the balance evaluations, the warm-up and the peers' wait; the readings' shapes."""
        self.robot = robot
        self.index = int(index)
        self.peers = tuple(int(p) for p in peers)
        self.dt_s = float(dt_s)
        self.update_every = int(update_every)
        self.warmup_steps = int(np.ceil(warmup_s / dt_s))
        self.history_steps = int(np.ceil(history_s / dt_s))
        self.regressor_every = int(regressor_every)
        self._reading_shapes = (
            ("accel_imu", (3,)),
            ("gyro_imu", (3,)),
            ("joint_pos_rad", (robot.n_joints,)),
            ("thrust_command", (6,)),
        )

    def _init_signal_filters(
        self, sensor_noise, kinematics_cutoff_hz, cutoff_hz, rate_cutoff_hz
    ) -> None:
        """The pre-, rate and product filters (``Preprocessor``), the slow filter of the
        momentum form's samples and the filters' memory (rollback and taint)."""
        robot, dt_s, regressor_every = self.robot, self.dt_s, self.regressor_every
        if np.shape(sensor_noise) != (3,):
            raise ValueError(f"sensor_noise must be 3 numbers, got {sensor_noise!r}")
        self.pre = Preprocessor(
            robot, dt_s, kinematics_cutoff_hz, encoder_std_rad=float(sensor_noise[2]),
            rate_cutoff_hz=rate_cutoff_hz,
        )  # fmt: skip
        self._imu_rot = np.asarray(robot.imu_rot, dtype=float)
        # Slow filter over the momentum form's samples (``momentum``), grasp frame.
        self.cutoff_hz = float(cutoff_hz)
        self.balance_filter = StateVariableFilter(MOMENTUM_SIZE, dt_s * regressor_every, cutoff_hz)
        # Memory of the filters: one delay (rollback after a gate) and four (taint).
        # (The momentum form's products pass the product filter, the pre-filter's twin; its rate
        # filter adds 3 / w = 0.03 s at 8 Hz, inside the taint's margin of four memories.)
        memory_s = self.pre.product_filter.delay_s + self.balance_filter.delay_s
        self.rollback_steps = int(np.ceil(memory_s / dt_s))
        self.taint_steps = int(np.ceil(4 * memory_s / dt_s))

    def _init_ukf(self, prior_params, prior_std, process_std_rel, gate_prob) -> None:
        """The UKF on the ten parameters: prior, its covariance, the random walk, the gate."""
        robot = self.robot
        prior = default_prior(robot) if prior_params is None else np.asarray(prior_params, float)
        gate = None if gate_prob is None else nis_gate(gate_prob)
        prior_cov = prior_covariance(prior, prior_std)
        process_cov = np.diag(process_std_rel**2 * np.diag(prior_cov))
        self.ukf = InertialParamUKF(prior, prior_cov, process_cov, gate_nis=gate)

    def _init_noise_model(
        self, force_std_n, torque_std_nm, actuation_noise, sensor_noise, peer_noise_std,
        localization_noise, cutoff_hz, kinematics_cutoff_hz,
    ) -> None:  # fmt: skip
        """The measurement covariance's model (``noise_model.NoiseModel``) and the fields the
        per-step path and the excitation designer read from it."""
        self.noise = NoiseModel(
            self.robot, self.dt_s, self.update_every, self.regressor_every, cutoff_hz,
            kinematics_cutoff_hz, force_std_n=force_std_n, torque_std_nm=torque_std_nm,
            actuation_noise=actuation_noise, sensor_noise=sensor_noise,
            peer_noise_std=peer_noise_std, localization_noise=localization_noise,
            mismatch_model_std=self._mismatch_model_std, rate_cutoff_hz=self.pre.rate_cutoff_hz,
            over_time=self.over_time_window > 0,
            accel_psd_ratio=None if self._fused is None else self._fused.error_ratio(
                self._localization_every),
        )  # fmt: skip
        n = self.noise
        self.meas_cov = n.floor_cov
        self.actuation_noise = n.actuation_noise
        self._actuation_abs, self._actuation_rel = n.actuation_abs, n.actuation_rel
        self._act_cov_sum = np.zeros((6, 6))
        self._act_cov_n = 0
        self._thrust_to_base = self.robot.thrust_to_base
        self._peer_noise_cov, self._peer_noise = n.peer_noise_cov, n.has_peer_noise
        # The encoders' noise squared in the momentum form's products of joint rates: its
        # fluctuation about the subtracted mean, per update (``rate_square_var``), and each
        # pending instant's vectors of it (``momentum.rate_square_terms``).
        self._rate_square_var = _cached_rate_square_var(
            self.dt_s, self.pre.rate_cutoff_hz, float(sensor_noise[2]), self.update_every
        )
        self._rate_terms: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _init_bookkeeping(self, relative_grasps, record: bool) -> None:
        """Counters, histories and the peers' relative grasps, at the start of a run."""
        self._grasp_lever = 0.0
        self.n_skipped_low_excitation = 0
        self._rot_world_base: np.ndarray | None = None  # (3, 3) base frame in world
        self._pos_world_base: np.ndarray | None = None
        self._last_input: tuple[np.ndarray, ...] | None = None
        self._tainted_until = -1
        self._pending: dict[int, Instant] = {}
        self._own_fix: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._peer_msgs: dict[int, dict[int, WrenchMessage]] = {}  # stamp -> sender -> message
        self._oldest_peer_msg = math.inf  # a lower bound of the stamps in _peer_msgs
        self._next_expiry = math.inf  # the oldest pending stamp after a full process (_expiring)
        self._changed = False  # an instant or a message arrived, or the peers changed
        self._relative: dict[int, RelativeGrasp] = {p: RelativeGrasp() for p in self.peers}
        self._layout = (None, None)  # (peers, their known transforms stacked: _balance_terms)
        for p, (rot, pos) in (relative_grasps or {}).items():
            if p not in self._relative:
                raise ValueError(f"relative_grasps names robot {p}, which is not a peer")
            self._relative[p].known = wrench_transform(np.asarray(rot), np.asarray(pos))
        self.stamp = -1
        self._window = None
        if self.over_time_window:
            self._window = UpdateWindow(
                self.noise.mode_lag_cov, self.over_time_window, self.update_every
            )
        self.record = bool(record)
        self.log: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.n_bad_readings = 0
        self.n_missing_imu = 0
        self.n_fixes = 0
        self.n_stale_messages = 0
        self.n_skipped_missing = 0
        self.n_skipped_tainted = 0
        self.n_skipped_peer_tainted = 0
        self.n_rolled_back = 0
        self.n_skipped_after_gate = 0
        self._gated_until = -1
        # (stamp, x, P, log length) before each of the latest accepted updates, for a rollback.
        self._snapshots: deque[tuple[int, np.ndarray, np.ndarray, int]] = deque(
            maxlen=self.rollback_steps // self.update_every + 1
        )

    def balance_layout_filter(self) -> StateVariableFilter:
        """A fresh slow filter like ``balance_filter`` over the ``Balance`` layout
        (``Balance.to_vector``: thrust, links, Y row by row): what the balance's entries go
        through after the products (the excitation designer's model of the estimator)."""
        return StateVariableFilter(Balance.SIZE, self.dt_s * self.regressor_every, self.cutoff_hz)

    # ------------------------------------------------------------------ inputs
    def step(self, stamp, accel_imu, gyro_imu, joint_pos_rad, thrust_command,
             base_pos_world=None, base_quat_world=None, *, servo_target_rate=None):  # fmt: skip
        """``EstimatorInputs.step``; with ``motion_lag_s`` the readings of ``motion_lag_s``
        earlier with the fused accelerometer (``fused_motion``), their message."""
        if self._fused is None:
            return super().step(
                stamp, accel_imu, gyro_imu, joint_pos_rad, thrust_command, base_pos_world,
                base_quat_world, servo_target_rate=servo_target_rate,
            )  # fmt: skip
        # Checked now, not a lag later.
        self._check_imu_frame(accel_imu, gyro_imu)
        self._check_shapes((accel_imu, gyro_imu, joint_pos_rad, thrust_command))
        late = self._fused.push(Reading(stamp, accel_imu, gyro_imu, joint_pos_rad,
                                        thrust_command, base_pos_world, base_quat_world,
                                        servo_target_rate))  # fmt: skip
        return None if late is None else self._feed(late)

    def _feed(self, r: Reading) -> WrenchMessage | None:
        """The pipeline's step (``EstimatorInputs.step``) on a reading out of the buffer."""
        return super().step(r.stamp, r.accel, r.gyro, r.q, r.thrust, r.pos, r.quat,
                            servo_target_rate=r.servo_rate)  # fmt: skip

    def flush(self) -> list[WrenchMessage]:
        """With ``motion_lag_s``: feed the buffered readings, smoothed on all the data
        (``FusedMotion.flush``), and return their messages (deliver them, then ``process``;
        ``fused_motion.flush_team`` interleaves this step by step for a team). Without: []."""
        return [m for m in self.flush_steps() if m is not None]

    def flush_steps(self) -> Iterator[WrenchMessage | None]:
        """``flush`` one buffered reading at a time: yields each one's message or None."""
        readings = [] if self._fused is None else self._fused.flush()
        for r in readings:
            yield self._feed(r)

    def robot_grasp_pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grasp frame in the base frame at joint angles ``q``."""
        return grasp_pose(self.robot, q)

    def receive(self, message: WrenchMessage) -> None:
        """Store a peer's message (messages from robots that are not peers are ignored; one
        older than the history, whose instant is already given up, is counted as stale)."""
        sender, stamp = message.sender, message.stamp
        rel = self._relative.get(sender)
        if rel is None:
            return
        if stamp < self.stamp - self.history_steps:
            self.n_stale_messages += 1
            return
        self._peer_msgs.setdefault(stamp, {})[sender] = message
        if stamp < self._oldest_peer_msg:
            self._oldest_peer_msg = stamp
        self._changed = True
        if rel.known is not None:
            return  # the grasp layout is given: no relative pose to average
        if message.fix and stamp in self._own_fix:
            self._accumulate_relative(sender, message)

    def _accumulate_relative(self, peer: int, msg: WrenchMessage) -> None:
        rot_wi, pos_wi = self._own_fix[msg.stamp]
        acc = self._relative[peer]
        acc.rot_sum += rot_wi.T @ msg.grasp_rot_world
        acc.pos_sum += rot_wi.T @ (msg.grasp_pos_world - pos_wi)
        acc.count += 1

    # ------------------------------------------------------------------ updates
    def process(self) -> int:
        """Update with every complete instant; skip the ones too old to wait. Returns the number
        of updates made plus the number rolled back (0: the estimate did not change)."""
        if not self._changed and not self._expiring():
            return 0  # what waits is still incomplete and no instant falls out of the history
        self._changed = False
        done = 0
        for stamp in sorted(self._pending):
            inst = self._pending[stamp]
            held = self._peer_msgs.get(stamp, _NO_MESSAGES)
            msgs = [held.get(p) for p in self.peers]
            ready = all(m is not None for m in msgs) and all(
                rel.known is not None or rel.count >= self.min_relative_fixes
                for rel in self._relative.values()  # one per peer
            )
            if ready:
                del self._pending[stamp]
                if inst.tainted:
                    self.n_skipped_tainted += 1
                    continue
                if any(m.tainted for m in msgs):
                    self.n_skipped_peer_tainted += 1
                    continue
                if not self._excited(inst.regressor):
                    self.n_skipped_low_excitation += 1
                    continue
                if stamp <= self._gated_until:
                    self.n_skipped_after_gate += 1
                    continue
                measurement, entry = self._measurement(stamp, inst, msgs)
                snapshot = (stamp, self.ukf.x.copy(), self.ukf.P.copy(), len(self.log))
                if self._reports is not None:
                    snapshot = (*snapshot, self._reports.state())
                self.ukf.predict()
                result = self.ukf.update_linear(*measurement)
                if result.accepted:
                    done += 1
                    self._snapshots.append(snapshot)
                    if self._window is not None:
                        self._window.add(entry)
                    elif entry is not None:
                        self._reports.add(stamp, measurement, entry, snapshot[2], self.ukf.Q)
                    if self.record:
                        self.log.append(measurement)
                elif result.reason == "gated":
                    done += self._roll_back(stamp)
                    self._gated_until = stamp + self.taint_steps
            elif stamp < self.stamp - self.history_steps:
                del self._pending[stamp]
                self.n_skipped_missing += 1
        self._forget_before(self.stamp - self.history_steps)
        return done

    def _measurement(self, stamp: int, inst: Instant, msgs: list):
        """The update's (z, Y, b, R): thrust_G = links_G + Y pi - sum_j T_ij W_j with
        z = thrust, b = links - peers' wrenches - the motion noise's mean, R its covariance
        (floors, actuation, motion, peers' noise, squared rates; ``_balance_terms``); with
        ``over_time_window`` conditioned on the window's updates (``over_time``), and the
        window's entry for it."""
        params = self.ukf.params_mean()
        if self._window is None:
            b, meas_cov, modes, *_ = self._balance_terms(inst, msgs, params)
        else:
            mean, cov, imu_map = self._over_time_noise(inst, msgs)
            b, meas_cov = self._peer_balance(inst, msgs, mean, cov)
        rate_cov = self._rate_square_cov(stamp, params)
        if rate_cov is not None:
            meas_cov = meas_cov + rate_cov
        measurement = (inst.thrust, inst.regressor, b, meas_cov)
        if self._window is None:
            return measurement, self._score_bias(inst, msgs, meas_cov, params, modes)
        return self._window.condition(stamp, *measurement, imu_map)

    def _balance_terms(self, inst: Instant, msgs: list, params: np.ndarray):
        """(b, R without squared-rate terms, own modes or None, E[n], Cov[n]) at ``params``, n
        the motion noise (``NoiseModel.motion_noise``): one compiled call (``instant_terms``)
        for a known grasp layout without the peers' noise; else ``_peer_balance``'s."""
        if self._layout[0] is not self.peers:  # ``known`` is set at construction only
            self._layout = (self.peers, known_transforms([self._relative[p] for p in self.peers]))
        transforms = self._layout[1]
        if not (
            self._peer_noise or self.motion_fusion == "none" or inst.motion_jac is None
            or transforms is None or any(m.motion_links_jac is None for m in msgs)
        ):  # fmt: skip
            condition = self.motion_fusion == "team" and bool(msgs)
            terms = instant_terms(self.noise, condition, params, inst, transforms, msgs,
                                  self.ukf.P, self.meas_cov, self.update_every)  # fmt: skip
            if terms is not None:
                return terms
        mean, cov = self.noise.motion_noise(
            self.motion_fusion, params, inst.motion_jac, inst.regressor, self._peer_motion(msgs),
            self._grasp_lever, own=self.noise.momentum_motion, params_cov=self.ukf.P,
        )  # fmt: skip
        return (*self._peer_balance(inst, msgs, mean, cov), None, mean, cov)

    def _peer_balance(self, inst: Instant, msgs: list, motion_mean, motion_cov):
        """b = links - sum_j T_j w_j - E[n] and R = floor + (act_cov + sum_j T_j C_j T_j^T) /
        update_every + Cov[n] + the peers' noise (``instant_terms.peer_terms``)."""
        peers, cov, added = self._peer_terms(inst.act_cov, msgs)
        meas_cov = self.meas_cov + cov / self.update_every + motion_cov + added
        return inst.links - peers - motion_mean, meas_cov

    def _peer_terms(self, act_cov: np.ndarray, msgs: list):
        """The peers' side of an instant's balance (``instant_terms.peer_terms``)."""
        rels = [self._relative[p] for p in self.peers]
        noise_cov = self._peer_noise_cov if self._peer_noise else None
        return peer_terms(act_cov, rels, msgs, noise_cov, self.noise)

    def _over_time_noise(self, inst: Instant, msgs: list):
        """The motion noise's mean, covariance and the team's IMU map, with the window
        (``NoiseModel.over_time_noise``)."""
        return self.noise.over_time_noise(
            self.motion_fusion, self.ukf.params_mean(), inst.motion_jac, inst.regressor,
            self._peer_motion(msgs), self._grasp_lever, params_cov=self.ukf.P,
        )  # fmt: skip

    def _score_bias(self, inst: Instant, msgs: list, cov, params, own=None):
        """``DeferredReports.modes`` of this update at ``params`` (None without the reports;
        ``own`` the own modes where already made; the peers' motion made only if needed)."""
        if self._reports is None:
            return None
        peers = functools.partial(self._peer_motion, msgs)
        return self._reports.modes(self.motion_fusion, params, inst, peers, cov, own)

    def _peer_motion(self, msgs: list) -> list:
        """Per peer, its wrench transform G_j -> G and its message (the noise model's peers)."""
        return [(self._relative[p].transform(), m) for p, m in zip(self.peers, msgs, strict=True)]

    def _rate_square_cov(self, stamp: int, params: np.ndarray) -> np.ndarray | None:
        """Covariance (6, 6) of the encoders' squared rate noise in this instant's own balance
        (links and regressor at the estimate ``params``): var sum_k w_k b_k b_k^T,
        b_k = Q_links + Q_Y pi of ``momentum.rate_square_terms``; None where the instant holds
        none (motion fusion takes them into its modes, ``EstimatorInputs._motion_fields``)."""
        entry = self._rate_terms.pop(stamp, None)
        if entry is None:
            return None
        terms, weights = entry
        b = terms[:, 12:18] + cargo_regressor_parts(terms)[1] @ params
        return self._rate_square_var * (b.T * weights) @ b

    def _forget_before(self, horizon: int) -> None:
        """Drop the peers' messages, own fixes and squared-rate terms of stamps before
        ``horizon`` (read for later stamps only: they may wait for the next full ``process``);
        keep the oldest pending stamp (``_next_expiry``: an instant is given up at its step)."""
        if self._oldest_peer_msg < horizon:
            for stamp in [s for s in self._peer_msgs if s < horizon]:
                del self._peer_msgs[stamp]
            self._oldest_peer_msg = min(self._peer_msgs, default=math.inf)
        # Own fixes, pending instants, squared-rate terms: in increasing stamp order.
        for old in (self._rate_terms, self._own_fix):
            while old and next(iter(old)) < horizon:
                del old[next(iter(old))]
        self._next_expiry = next(iter(self._pending), math.inf)

    def _roll_back(self, gated_stamp: int) -> int:
        """Undo the updates of the instants within the filters' memory before ``gated_stamp``;
        returns how many."""
        undo = [s for s in self._snapshots if s[0] >= gated_stamp - self.rollback_steps]
        if not undo:
            return 0
        first, x, cov, log_len, *reports = undo[0]
        if reports:
            self._reports.restore(reports[0])
        if self._window is not None:
            self._window.drop_from(first)
        # The predictions of the undone instants and of the gated one stay: P grows as if the
        # instants had been skipped.
        self.ukf.x = x
        self.ukf.P = cov + (len(undo) + 1) * self.ukf.Q
        del self.log[log_len:]
        for _ in undo:
            self._snapshots.pop()
        self.n_rolled_back += len(undo)
        return len(undo)

    def _excited(self, regressor: np.ndarray) -> bool:
        """Does the filtered motion of this instant stand above the noise of its measurement?"""
        return self.noise.excitation_snr(regressor, self._grasp_lever) >= self.min_excitation_snr

    def sensor_cov_at(self, params: np.ndarray, lever_m: float | np.ndarray) -> np.ndarray:
        """Measurement covariance (..., 6, 6) of the sensors' noise, scalar per block, at the cargo
        ``params`` (10,) and base-to-grasp lever(s) ``lever_m`` (``NoiseModel.sensor_cov_at``);
        the excitation designer reads it."""
        return self.noise.sensor_cov_at(params, lever_m)

    def set_peers(self, peers: list[int] | tuple[int, ...]) -> None:
        """Change which robots hold the cargo (a robot released it). The pending instants are
        given up (counted as ``skipped_missing``), and the instants within the filters' memory
        of the change are skipped as tainted: they mix the balance of two different subsystems."""
        peers = tuple(int(p) for p in peers)
        if self.index in peers:
            raise ValueError(f"robot {self.index} cannot be its own peer")
        self.peers = peers
        self._relative = {p: self._relative.get(p, RelativeGrasp()) for p in self.peers}
        self.n_skipped_missing += len(self._pending)
        self._pending.clear()
        self._changed = True
        if self._window is not None:
            self._window.clear()  # the team's IMU channels change
        self._tainted_until = max(self._tainted_until, self.stamp + self.taint_steps)

    # ------------------------------------------------------------------ outputs
    def params_mean(self) -> np.ndarray:
        """Estimated cargo parameters pi (10,) in this robot's grasp frame."""
        return self.ukf.params_mean(
            None if self._reports is None else self._reports.offset(self.ukf)
        )

    def physical_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation of [m, c_x, c_y, c_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz]
        (kg, m, kg m^2; inertia about the centre of mass, grasp-frame axes): the reported
        (physically consistent) body and the posterior's spread carried to these quantities
        (`InertialParamUKF.physical_estimate`)."""
        offset = None if self._reports is None else self._reports.offset(self.ukf)
        return self.ukf.physical_estimate(offset=offset, cov=self.params_cov())

    def params_cov(self) -> np.ndarray:
        cov = self.ukf.params_cov()
        return cov if self._reports is None else self._reports.covariance(cov)

    def params_std(self, out: np.ndarray | None = None) -> np.ndarray:
        """sqrt(diag(``params_cov``)) (10,), into ``out`` where given, without its copy of P nor
        the reports' full product (``DeferredReports.std``)."""
        out = np.empty(10) if out is None else out
        if self._reports is None:
            np.sqrt(self.ukf.P.diagonal(), out=out)
        else:
            self._reports.std(self.ukf.P, out)
        return out

    @property
    def counters(self) -> dict[str, int]:
        return {
            "updates": self.ukf.n_updates,
            "skipped_missing": self.n_skipped_missing,
            "skipped_bad_reading": self.n_skipped_tainted + self.ukf.n_skipped_nonfinite,
            "gated": self.ukf.n_gated,
            "mode_fallbacks": self.ukf.n_mode_fallbacks,
            "skipped_low_excitation": self.n_skipped_low_excitation,
            "skipped_peer_tainted": self.n_skipped_peer_tainted,
            "skipped_after_gate": self.n_skipped_after_gate,
            "rolled_back": self.n_rolled_back,
            "bad_readings": self.n_bad_readings,
            "missing_imu": self.n_missing_imu,
            "fixes": self.n_fixes,
            "stale_messages": self.n_stale_messages,
            "pending": len(self._pending),
        }


# ---------------------------------------------------------------------------------------------
