"""One control step of a ``CargoEstimator`` on its common path, compiled as one call.

When every reading of the step is present and finite, the estimator's per-step work is

1. the pre-filter step (``preprocess.Preprocessor``): u = T [gyro; accel; q; thrust], then
   x_k+1 = Ad x_k + b_value u_prev + b_slope (u - u_prev), u_prev = u on the held channels;
2. the momentum form's chain (``momentum``): the rate filter's step on the same u, one sample
   [thrust_G; P_links; Q_links; the cargo's P and Q arguments] of its outputs, and the product
   filter's step on it;
3. the attitude (base frame B in world): from the localization fix when there is a usable one,
   R_WB = R(quat), else propagated with the gyro, R_WB <- R_WB exp([R_BI w_imu dt]x);
4. on every ``regressor_every``-th step, the per-step covariance of the actuation noise carried
   into the grasp frame G (at the rate filter's joint angles),
       Sigma_G += T_GB T_BS diag(std^2) T_BS^T T_GB^T,   std = abs + rel |command|,
   and one step of the slow balance filter on the product filter's value; the balance is
   read out of it at the update instants (``momentum.balance_from_filtered``).

``estimator_step`` does all of that in place on the estimator's arrays; its inputs are the
readings as they come (IMU body axes, rad, m, N and N m) and it changes nothing when a reading
is missing, non-finite or wrongly shaped (the estimator's Python path handles those). The
equations are those of ``preprocess``, ``momentum`` and ``geometry``, whose compiled functions
it calls; the Python path calls the same compiled sample (``momentum``).

``EstimatorInputs`` is the input side of ``CargoEstimator`` (its ``step``): it takes this call
when it can and the Python path otherwise, and records the instants of the updates. Before
either, given the rate of the robot's servo targets, it takes the change of the servos' ripple
off the accelerometer's period mean (``momentum`` module docstring, Servo ripple): inside
``estimator_step`` (``servo_ripple_step``) on the steps whose ripple map is kept, in Python on
those that refresh it (update instants) and on the Python path.
"""

from __future__ import annotations

import math

import numpy as np
from numba import boolean, float64, int64, njit, typeof, types

from .checks import all_finite
from .copies import deepcopy_state
from .geometry import exp_so3, quat_to_mat
from .instant_kernels import message_pose, robot_record, servo_ripple_of
from .messages import Instant, WrenchMessage
from .momentum import balance_from_filtered, rate_square_terms
from .preprocess import first_order_hold_step
from .rate_square import rate_square_links_cov
from .records import as_interned, record_of
from .rne import RobotArrays
from .step_parts import (
    BAD_FIX,
    FIX,
    NOT_USABLE,
    RIPPLE_MOVING,
    actuation_cov_into,
    actuation_cov_step,
    momentum_step,
    pre_filter_input,
    readings_usable,
    ripple_case,
    servo_ripple_step,
    update_attitude,
)

# What the compiled step reads as the fix when there is none (it is not used).
_NO_POS, _NO_QUAT = np.zeros(3), np.zeros(4)
# What it reads as the servo ripple's map, rate and last ripple without one (not used).
_NO_MAP, _NO_RATE, _UNUSED_ACCEL = np.zeros((3, 0)), np.zeros(0), np.zeros(3)


_V, _M, _T3 = float64[::1], float64[:, ::1], float64[:, :, ::1]
_BOOLS = boolean[::1]
_STEP_SIGNATURE = types.Tuple((int64, float64))(
    int64[::1], _M, _T3, _M, _V, _M, _T3, int64, _M, _V,  # RobotArrays
    _M, _M, _V, _V, _BOOLS,  # pre-filter constants
    _M, _V, _V, _BOOLS, _M, _V, _V, _BOOLS,  # rate and product filter constants
    _V, _V,  # IMU position, joint-rate noise variance
    _M, _V, _V, _BOOLS,  # balance filter constants
    _M, _M, _V, _V, float64,  # IMU rotation, thrust site, actuation noise, dt
    _M, _V, _M, _V, _M, _V, _M, _V,  # filter states and previous inputs
    _M, _M, _V,  # actuation covariance sum, attitude
    _V, _V, _V, _V, _V, _V, boolean, boolean,  # readings, flags
    _M, _V, _V, _V, boolean,  # servo ripple: map, targets' rate, last ripple, corrected accel, flag
)  # fmt: skip


@njit(_STEP_SIGNATURE, cache=True)
def estimator_step_arrays(
    parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
    grasp_rot, grasp_pos, pre_to_input, pre_ad, pre_b_value, pre_b_slope, pre_held,
    rate_ad, rate_b_value, rate_b_slope, rate_held, prod_ad, prod_b_value, prod_b_slope,
    prod_held, imu_pos, qd_var, bal_ad, bal_b_value, bal_b_slope, bal_held, imu_rot,
    thrust_to_base, act_abs, act_rel, dt_s, pre_state, pre_u_prev, rate_state, rate_u_prev,
    prod_state, prod_u_prev, bal_state, bal_u_prev, act_cov_sum, rot_world_base,
    pos_world_base, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix, do_balance,
    ripple_map, target_rate, ripple_prev, accel_out, with_ripple,
):  # fmt: skip
    """One common-path step (module docstring), in place on the filters' states and previous
    inputs, the actuation covariance sum and the attitude. Every filter must be started and the
    attitude known. With ``with_ripple``, the accelerometer's reading is first taken less the
    servos' ripple (``servo_ripple_step`` with ``ripple_map`` and ``target_rate``, from
    ``ripple_prev``, which then holds this step's ripple), as
    ``EstimatorInputs._without_servo_ripple`` does; the reading used is written to
    ``accel_out``. Returns (outcome, lever |p_BG| m or NaN when no balance was filtered);
    outcome NOT_USABLE leaves everything unchanged."""
    nj = parent.shape[0] - 1
    if not readings_usable(nj, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix):
        return NOT_USABLE, np.nan
    moving = (
        with_ripple
        and target_rate.shape[0] == nj
        and ripple_case(target_rate, ripple_prev, q) == RIPPLE_MOVING
    )
    if moving:
        ripple, accel = servo_ripple_step(
            ripple_map, target_rate, ripple_prev, imu_rot, dt_s, accel
        )
        if not all_finite(accel):
            return NOT_USABLE, np.nan
        ripple_prev[:] = ripple
    accel_out[:] = accel
    arrays = RobotArrays(
        parent, joint_axis, rot_in_parent, pos_in_parent, mass, com, inertia_com, grasp_link,
        grasp_rot, grasp_pos,
    )  # fmt: skip
    u = pre_filter_input(pre_to_input, gyro, accel, q, thrust)
    first_order_hold_step(pre_ad, pre_b_value, pre_b_slope, pre_held, pre_state, pre_u_prev, u)
    grasp_from_base, pos_bg = momentum_step(
        arrays, imu_pos, qd_var, rate_ad, rate_b_value, rate_b_slope, rate_held, rate_state,
        rate_u_prev, prod_ad, prod_b_value, prod_b_slope, prod_held, prod_state, prod_u_prev, u,
    )  # fmt: skip
    outcome = update_attitude(
        rot_world_base, pos_world_base, imu_rot, gyro, dt_s, fix_pos, fix_quat, has_fix
    )
    if not do_balance:
        return outcome, np.nan
    lever = actuation_cov_into(
        grasp_from_base, pos_bg, thrust_to_base, act_abs, act_rel, act_cov_sum, thrust
    )
    sample = np.ascontiguousarray(prod_state[0])
    first_order_hold_step(bal_ad, bal_b_value, bal_b_slope, bal_held, bal_state, bal_u_prev, sample)
    return outcome, lever


# ``estimator_step_arrays``' constant arguments, in its order: the fields of
# ``estimator_constants``.
CONSTANT_FIELDS = (
    *RobotArrays._fields, "pre_to_input", "pre_ad", "pre_b_value", "pre_b_slope", "pre_held",
    "rate_ad", "rate_b_value", "rate_b_slope", "rate_held", "prod_ad", "prod_b_value",
    "prod_b_slope", "prod_held", "imu_pos", "qd_var", "bal_ad", "bal_b_value", "bal_b_slope",
    "bal_held", "imu_rot", "thrust_to_base", "act_abs", "act_rel", "dt_s",
)  # fmt: skip


def estimator_constants(values: tuple) -> np.ndarray:
    """``estimator_step_arrays``' constant arguments ``values`` (in ``CONSTANT_FIELDS`` order) as
    one record (``records.record_of``; the scalars grasp_link and dt_s as arrays of one), ready
    for ``estimator_step`` (``packed_ready``)."""
    fields = {name: np.atleast_1d(v) for name, v in zip(CONSTANT_FIELDS, values, strict=True)}
    return packed_ready(record_of(fields))


# The ids of the interned dtypes ``estimator_step`` is compiled for (interned dtypes live on, so
# their ids are never reused).
_READY_LAYOUTS: set[int] = set()


def packed_ready(constants: np.ndarray) -> np.ndarray:
    """``constants`` (``estimator_constants``; also one copied or unpickled, whose dtype may be
    a new object) with its dtype ``interned``, and ``estimator_step`` compiled for its layout.
    Each layout is compiled here, never at a call: a call with other argument types raises
    TypeError, as ``estimator_step_arrays``' signature does."""
    if id(constants.dtype) in _READY_LAYOUTS:  # a deep copy keeps its dtype object
        return constants
    constants = as_interned(constants)
    signature = _STEP_SIGNATURE.return_type(
        typeof(constants), *_STEP_SIGNATURE.args[len(CONSTANT_FIELDS) :]
    )
    if signature.args not in estimator_step.overloads:
        estimator_step.disable_compile(False)
        try:
            estimator_step.compile(signature)
        finally:
            estimator_step.disable_compile(True)
    _READY_LAYOUTS.add(id(constants.dtype))
    return constants


@njit(cache=True, inline="always")
def _bools(stored: np.ndarray) -> np.ndarray:
    """A record's bool field (stored as uint8 0 or 1, ``records``) viewed as bool."""
    return stored[:].view(np.bool_)


@njit(cache=True)
def estimator_step(
    constants, pre_state, pre_u_prev, rate_state, rate_u_prev, prod_state, prod_u_prev,
    bal_state, bal_u_prev, act_cov_sum, rot_world_base, pos_world_base, accel, gyro, q, thrust,
    fix_pos, fix_quat, has_fix, do_balance, ripple_map, target_rate, ripple_prev, accel_out,
    with_ripple,
):  # fmt: skip
    """``estimator_step_arrays`` with its constant arguments as one record
    (``estimator_constants``): the same call, its constants passed across the Python boundary
    as one argument."""
    c = constants[0]
    return estimator_step_arrays(
        c.parent[:], c.joint_axis[:], c.rot_in_parent[:], c.pos_in_parent[:], c.mass[:],
        c.com[:], c.inertia_com[:], c.grasp_link[0], c.grasp_rot[:], c.grasp_pos[:],
        c.pre_to_input[:], c.pre_ad[:], c.pre_b_value[:], c.pre_b_slope[:], _bools(c.pre_held),
        c.rate_ad[:], c.rate_b_value[:], c.rate_b_slope[:], _bools(c.rate_held), c.prod_ad[:],
        c.prod_b_value[:], c.prod_b_slope[:], _bools(c.prod_held), c.imu_pos[:], c.qd_var[:],
        c.bal_ad[:], c.bal_b_value[:], c.bal_b_slope[:], _bools(c.bal_held), c.imu_rot[:],
        c.thrust_to_base[:], c.act_abs[:], c.act_rel[:], c.dt_s[0], pre_state, pre_u_prev,
        rate_state, rate_u_prev, prod_state, prod_u_prev, bal_state, bal_u_prev, act_cov_sum,
        rot_world_base, pos_world_base, accel, gyro, q, thrust, fix_pos, fix_quat, has_fix,
        do_balance, ripple_map, target_rate, ripple_prev, accel_out, with_ripple,
    )  # fmt: skip


class EstimatorInputs:
    """The input side of ``CargoEstimator``: ``step`` and the recording of update instants.
    It uses the estimator's filters (``pre``, ``balance_filter`` over the momentum form's
    channels), attitude, actuation
    covariance sum, counters and histories, which ``CargoEstimator.__init__`` creates."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    # A copied or unpickled estimator (another process) readies its constants' records again
    # (their dtypes may be new objects).
    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if "_step_constants" in state:
            self._step_constants = packed_ready(self._step_constants)
        if "_robot_record" in state:
            self._robot_record = as_interned(self._robot_record)

    def _init_constants(self) -> None:
        """The constant records of the compiled calls, made once (a copy keeps them):
        ``estimator_step``'s (``_compiled_step_constants``) and the robot's
        (``instant_kernels.robot_record``, for ``message_pose`` and ``servo_ripple_of``)."""
        self._step_constants = self._compiled_step_constants()
        self._robot_record = robot_record(self.robot)

    def _compiled_step_constants(self) -> np.ndarray:
        """The constant arguments of ``estimator_step_arrays`` as one record
        (``estimator_constants``)."""
        pre, bal = self.pre.filter, self.balance_filter
        rate, prod = self.pre.rate_filter, self.pre.product_filter

        def c(a):
            return np.ascontiguousarray(a, dtype=float)

        def f(filt):
            return filt.ad, filt.b_value, c(filt.b_slope), filt._held

        return estimator_constants(
            (
                *self.robot.arrays, c(self.pre._to_input), *f(pre), *f(rate), *f(prod),
                c(self.pre._imu_pos), c(self.pre.qd_var), *f(bal), c(self._imu_rot),
                c(self._thrust_to_base), c(self._actuation_abs), c(self._actuation_rel),
                self.dt_s,
            )
        )  # fmt: skip

    def step(
        self,
        stamp: int,
        accel_imu: np.ndarray | None,
        gyro_imu: np.ndarray | None,
        joint_pos_rad: np.ndarray,
        thrust_command: np.ndarray,
        base_pos_world: np.ndarray | None = None,
        base_quat_world: np.ndarray | None = None,
        *,
        servo_target_rate: np.ndarray | None = None,
    ) -> WrenchMessage | None:
        """Ingest the readings of control step ``stamp``; return the message to publish, if any.

        ``accel_imu`` and ``gyro_imu`` None: the IMU frame is missing (see the module docstring).
        ``servo_target_rate`` (n_joints,) rad/s: the rate at which this robot's servo targets
        moved over the period that ends now; given, the accelerometer's period mean is read less
        the servos' ripple it holds (``_without_servo_ripple``).
        """
        if (accel_imu is None) != (gyro_imu is None):
            self._check_imu_frame(accel_imu, gyro_imu)
        # The ripple goes into the compiled call once its map is there (refreshed first at an
        # instant).
        instant = stamp % self.update_every == 0
        ripple_rate = None
        if servo_target_rate is not None:
            if instant and self._servo_ripple_map is not None:
                self._refresh_servo_ripple_map(joint_pos_rad, servo_target_rate)
            if self._servo_ripple_map is None:
                accel_imu = self._without_servo_ripple(
                    stamp, accel_imu, joint_pos_rad, servo_target_rate
                )
            else:
                ripple_rate = servo_target_rate
        if accel_imu is not None and stamp > self.stamp and self._compiled_path_ready(stamp):
            outcome = self._compiled_step(
                stamp, accel_imu, gyro_imu, joint_pos_rad, thrust_command, base_pos_world,
                base_quat_world, ripple_rate,
            )  # fmt: skip
            if outcome != NOT_USABLE:
                return self.instant_after_compiled_step(stamp, outcome, joint_pos_rad)
        if ripple_rate is not None:  # the compiled call changed nothing: the ripple here
            accel_imu = self._without_servo_ripple(stamp, accel_imu, joint_pos_rad, ripple_rate)
        return self._python_step(
            stamp, accel_imu, gyro_imu, joint_pos_rad, thrust_command, base_pos_world,
            base_quat_world,
        )  # fmt: skip

    # The IMU point's servo ripple at the last sample instant, and its map from the servo
    # targets' rate (``_without_servo_ripple``).
    _servo_ripple_prev: np.ndarray | None = None
    _servo_ripple_map: np.ndarray | None = None

    def _without_servo_ripple(self, stamp, accel_imu, joint_pos_rad, target_rate):
        """The accelerometer's period mean less the servos' ripple (``momentum`` module
        docstring, Servo ripple): a_k - R_BI^T (v_r(t_k) - v_r(t_k-1)) / dt, v_r = V rate with
        V (``momentum.servo_ripple_velocities``, at the current cargo estimate) refreshed at each
        update instant (every ``update_every`` steps: it follows the slow configuration).
        Unusable joint angles or rates (the Python path handles the readings) leave the reading
        and the last ripple as they are."""
        rate, q = self._ripple_inputs(joint_pos_rad, target_rate)
        if rate is None:
            return accel_imu  # at rest (a NaN rate is not: it counts as nonzero), or unusable
        if self._servo_ripple_map is None or stamp % self.update_every == 0:
            self._servo_ripple_map = self._servo_ripple_map_at(q)
        if self._servo_ripple_map is None:
            return accel_imu  # the servos' gains are unknown
        if accel_imu is None:
            self._servo_ripple_prev = self._servo_ripple_map @ rate
            return None
        self._servo_ripple_prev, corrected = servo_ripple_step(
            self._servo_ripple_map, rate, self._servo_ripple_prev, self._imu_rot, self.dt_s,
            np.asarray(accel_imu, dtype=float),
        )  # fmt: skip
        return corrected

    def _ripple_inputs(self, joint_pos_rad, target_rate):
        """The targets' rate and the joint angles (float arrays) when the ripple changes this
        step (``ripple_case`` RIPPLE_MOVING, both of n_joints), else (None, None); the last
        ripple made zero if there is none yet."""
        rate = np.asarray(target_rate, dtype=float)
        q = np.asarray(joint_pos_rad, dtype=float)
        nj = (self.robot.n_joints,)
        if self._servo_ripple_prev is None:
            self._servo_ripple_prev = np.zeros(3)
        if rate.shape != nj or q.shape != nj:
            return None, None
        if ripple_case(rate, self._servo_ripple_prev, q) != RIPPLE_MOVING:
            return None, None
        return rate, q

    def _servo_ripple_map_at(self, q: np.ndarray) -> np.ndarray | None:
        """``momentum.servo_ripple_velocities`` at joint angles ``q`` (n_joints,) rad and the
        current cargo estimate (``instant_kernels.servo_ripple_of``); None when the servos'
        gains are unknown."""
        if self.robot.servo_gain is None:
            return None
        cargo, q = self.ukf.params_mean(), np.ascontiguousarray(q, dtype=float)
        return servo_ripple_of(self._robot_record, q, cargo, float(self.dt_s))

    def _refresh_servo_ripple_map(self, joint_pos_rad, target_rate) -> None:
        """At an update instant, the servos' ripple map refreshed (``_servo_ripple_map_at``) if
        the ripple changes this step, as ``_without_servo_ripple`` does, so that the compiled
        step then takes the ripple off (``estimator_step``)."""
        rate, q = self._ripple_inputs(joint_pos_rad, target_rate)
        if rate is not None:
            self._servo_ripple_map = self._servo_ripple_map_at(q)

    # Whether the filters are started and the attitude known: once so, they stay so.
    _filters_ready = False
    # ``estimator_step``'s state arguments (the filters' states and previous inputs, which
    # they change in place only), gathered at the first compiled step.
    _step_states: tuple[np.ndarray, ...] | None = None

    def _compiled_path_ready(self, stamp: int) -> bool:
        """With an IMU frame and an increasing stamp, can this step take ``estimator_step``:
        the filters started (the balance filter if this step feeds it) and an attitude?"""
        if self._filters_ready:
            return True
        if self._rot_world_base is None or not self.pre.filter.started:
            return False
        if self.balance_filter.started:
            self._step_states = self._filter_states()
            self._filters_ready = True
            return True
        return stamp % self.regressor_every != 0

    def _filter_states(self) -> tuple[np.ndarray, ...]:
        """``estimator_step``'s state arguments: each filter's state and previous input."""
        filters = (self.pre.filter, self.pre.rate_filter, self.pre.product_filter)
        return tuple(a for f in (*filters, self.balance_filter) for a in (f.state, f._u_prev))

    def _compiled_step(self, stamp, accel, gyro, q, thrust, pos, quat, ripple_rate) -> int:
        """The common path in one compiled call (``per_step``), with the servos' ripple taken
        off the accelerometer first when ``ripple_rate`` (the targets' rate) is given; NOT_USABLE
        (nothing changed) for a non-finite or wrongly shaped reading, or readings not float64
        vectors."""
        do_balance = stamp % self.regressor_every == 0
        fix_given = pos is not None and quat is not None
        if not fix_given:
            pos, quat = _NO_POS, _NO_QUAT
        states = self._step_states
        if states is None:  # the balance filter not started yet (nor fed on this step)
            states = self._filter_states()
        with_ripple = ripple_rate is not None
        accel_used = np.empty(3) if with_ripple else accel
        try:
            outcome, lever = estimator_step(
                self._step_constants, *states, self._act_cov_sum, self._rot_world_base,
                self._pos_world_base, accel, gyro, q, thrust, pos, quat, fix_given, do_balance,
                self._servo_ripple_map if with_ripple else _NO_MAP,
                ripple_rate if with_ripple else _NO_RATE,
                self._servo_ripple_prev if with_ripple else _NO_RATE,
                accel_used if with_ripple else _UNUSED_ACCEL, with_ripple,
            )  # fmt: skip
        except TypeError:  # not float64 vectors: the Python path converts them
            return NOT_USABLE
        if outcome != NOT_USABLE:
            self._last_input = (accel_used, gyro, q, thrust)
            self._count_compiled_step(stamp, outcome, lever, do_balance)
        return outcome

    def instant_after_compiled_step(self, stamp, outcome, joint_pos_rad) -> WrenchMessage | None:
        """After a compiled step of ``outcome`` (not NOT_USABLE) at ``stamp``: at an update
        instant past the warm-up, the instant recorded (``_record_instant``, with the joint
        angles ``joint_pos_rad``) and its message; else None."""
        if stamp % self.update_every or stamp < self.warmup_steps:
            return None
        return self._record_instant(stamp, joint_pos_rad, outcome == FIX)

    def _count_compiled_step(self, stamp, outcome, lever, do_balance) -> None:
        """The stamp and the counters after a compiled step of ``outcome`` (not NOT_USABLE) and
        ``lever``."""
        self.stamp = int(stamp)
        if outcome == FIX:
            self.n_fixes += 1
        elif outcome == BAD_FIX:
            self.n_bad_readings += 1
        if do_balance:
            self._act_cov_n += 1
            self._grasp_lever = lever

    @staticmethod
    def _check_imu_frame(accel_imu, gyro_imu) -> None:
        """ValueError unless the accelerometer and the gyro are both given or both None."""
        if (accel_imu is None) != (gyro_imu is None):
            raise ValueError("accel_imu and gyro_imu are one IMU frame: both None or neither")

    def _check_shapes(self, readings) -> None:
        """ValueError unless each of (accel, gyro, q, thrust) is None or of its shape."""
        for (name, shape), x in zip(self._reading_shapes, readings, strict=True):
            if x is not None and np.shape(x) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {np.shape(x)}")

    def _python_step(
        self, stamp, accel_imu, gyro_imu, joint_pos_rad, thrust_command, base_pos_world,
        base_quat_world,
    ) -> WrenchMessage | None:  # fmt: skip
        """``step`` for any readings: missing or non-finite ones held, the filters started."""
        missing = accel_imu is None
        readings = [
            None if x is None else np.asarray(x, dtype=float)
            for x in (accel_imu, gyro_imu, joint_pos_rad, thrust_command)
        ]
        self._check_shapes(readings)
        if stamp <= self.stamp:
            raise ValueError(f"stamps must increase: got {stamp} after {self.stamp}")
        self.stamp = int(stamp)
        # One check for the usual case (every reading present and finite), then per reading;
        # the readings in one vector serve the pre-filter too.
        usable = [True] * 4
        raw = None if missing else self.pre.raw_input(*readings)
        if raw is None or not np.isfinite(raw).all():
            usable = [x is not None and bool(np.all(np.isfinite(x))) for x in readings]
        if not all(usable):
            if missing:
                self.n_missing_imu += 1
            if any(x is not None and not ok for x, ok in zip(readings, usable, strict=True)):
                self.n_bad_readings += 1
            self._tainted_until = stamp + self.taint_steps
            if self._last_input is None:
                return None
            # Hold the previous sample of each unusable signal only.
            readings = [
                x if ok else last
                for x, ok, last in zip(readings, usable, self._last_input, strict=True)
            ]
            raw = self.pre.raw_input(*readings)
        self._last_input = tuple(readings)
        accel, gyro, q, thrust = readings
        self.pre.step_raw(raw)
        fix = self._update_attitude(gyro, base_pos_world, base_quat_world)
        if stamp % self.regressor_every == 0:
            self._filter_balance(thrust)
        if stamp % self.update_every or stamp < self.warmup_steps:
            return None
        return self._record_instant(stamp, q, fix)

    def _filter_balance(self, thrust_command: np.ndarray) -> None:
        """The actuation covariance of this step and the slow filter's step on the product
        filter's value (the momentum form's samples, low-passed)."""
        rot_bg, pos_bg = self.pre.grasp_pose
        self._grasp_lever = actuation_cov_step(
            rot_bg, pos_bg, np.ascontiguousarray(self._thrust_to_base), self._actuation_abs,
            self._actuation_rel, self._act_cov_sum, np.ascontiguousarray(thrust_command),
        )  # fmt: skip
        self._act_cov_n += 1
        self.balance_filter.step(self.pre.product_filter.state[0])

    def _update_attitude(self, gyro_imu, base_pos_world, base_quat_world) -> bool:
        """Attitude from the last fix, propagated with the gyro between fixes."""
        if base_quat_world is not None and base_pos_world is not None:
            quat = np.asarray(base_quat_world, dtype=float)
            pos = np.asarray(base_pos_world, dtype=float)
            if quat.shape != (4,) or pos.shape != (3,):
                raise ValueError("base_pos_world must be (3,) and base_quat_world (4,)")
            if np.all(np.isfinite(quat)) and np.all(np.isfinite(pos)) and np.linalg.norm(quat) > 0:
                self._rot_world_base = np.ascontiguousarray(quat_to_mat(quat))
                self._pos_world_base = np.array(pos, dtype=float)
                self.n_fixes += 1
                return True
            self.n_bad_readings += 1
        if self._rot_world_base is not None:
            w_base = self._imu_rot @ gyro_imu
            self._rot_world_base = self._rot_world_base @ exp_so3(self.dt_s * w_base)
        return False

    def _rate_square_q(self) -> np.ndarray | None:
        """The rate filter's joint angles (n_joints,) rad, where the encoders' squared rate noise
        (``rate_square.rate_square_var``) is taken at this instant; None when it is off."""
        if self._rate_square_var <= 0:
            return None
        return self.pre.rate_filter.state[0, 6 : 6 + self.robot.n_joints]

    def _motion_fields(self, b, stamp: int, q_rate) -> tuple[tuple | None, dict]:
        """The instant's sensor-noise modes in the momentum chain
        (``NoiseModel.momentum_jacobians``, with the squared rate noise at joint angles
        ``q_rate``, ``_rate_square_q``; None without motion fusion) and the message's motion fields
        (``NoiseModel.message_modes``), both from ``NoiseModel.instant_modes``."""
        if self.motion_fusion == "none":
            return None, {}
        # The squared rate noise joins the modes (``NoiseModel.momentum_jacobians``): it enters
        # the team's mismatch too, and neither the message's covariance nor
        # ``_rate_square_cov`` carries it then.
        rate_at = None if q_rate is None else (q_rate, self._rate_square_var)
        jac, (links, grasp, var) = self.noise.instant_modes(
            stamp, b.regressor, self.pre.filter.state, rate_at=rate_at
        )
        motion = {
            "grasp_acc": b.regressor[:3, 0].copy(),
            "motion_links_jac": links,
            "motion_grasp_jac": grasp,
            "motion_var": var,
            "motion_band": var,
        }
        return jac, motion

    def _expiring(self) -> bool:
        """Does a pending instant fall before the history's horizon, so that ``process`` has to
        give it up? Asked only while nothing arrived (``_changed`` False), so the oldest pending
        stamp as ``process`` last left it (``_next_expiry``) still bounds them: whatever arrives
        sets ``_changed``. The peers' messages, own fixes and squared-rate terms older than the
        horizon are read for no later stamp; they wait for the next full ``process``."""
        return self._next_expiry < self.stamp - self.history_steps

    def quiet_through(self) -> float:
        """The last stamp through which ``process`` returns 0 (changes nothing) as long as
        nothing arrives and nothing changes but the stamp (no ``receive``, no instant recorded,
        the same peers): -inf when something has (``_changed``), else the last stamp at which
        no pending instant falls before the history's horizon (``_expiring`` False)."""
        return -math.inf if self._changed else self._next_expiry + self.history_steps

    def _record_instant(self, stamp: int, q_raw: np.ndarray, fix: bool) -> WrenchMessage | None:
        # H[Z] = H'[P] + H[Q] from the slow filter's value and derivative (``momentum``).
        b = balance_from_filtered(self.balance_filter.state[0], self.balance_filter.state[1])
        wrench_grasp = b.thrust - b.links
        # Per-step actuation covariance averaged over this update's window (grasp frame).
        act_cov = self._act_cov_sum / max(self._act_cov_n, 1)
        self._act_cov_sum[...] = 0.0  # in place: the team record's row stays its view
        self._act_cov_n = 0
        tainted = stamp <= self._tainted_until
        q_rate = self._rate_square_q()
        jac, motion = self._motion_fields(b, stamp, q_rate)
        sent_cov = act_cov
        if jac is None:  # the regressor's part waits with the instant (``_rate_square_cov``)
            rate_terms = None if q_rate is None else rate_square_terms(self.robot, q_rate)
            rate_cov = rate_square_links_cov(rate_terms, self._rate_square_var, self.update_every)
            sent_cov = act_cov + rate_cov
            if rate_terms is not None:
                self._rate_terms[stamp] = rate_terms
        self._changed = True
        self._pending[stamp] = Instant(  # b's arrays are new (``balance_from_filtered``)
            thrust=b.thrust,
            links=b.links,
            regressor=b.regressor,
            act_cov=act_cov,
            tainted=tainted,
            motion_jac=jac,
        )
        if self._rot_world_base is None:
            return None  # no attitude yet: nothing meaningful to publish
        # The grasp pose for the relative-grasp average uses the current encoders, not the
        # filtered (delayed) angles, so that it matches the fix in time.
        rot_wg, pos_wg, wrench_world = message_pose(
            self._robot_record, np.ascontiguousarray(q_raw, dtype=float), self._rot_world_base,
            self._pos_world_base, wrench_grasp,
        )  # fmt: skip
        if fix:
            self._own_fix[stamp] = (rot_wg, pos_wg)
            held = self._peer_msgs.get(stamp, {})
            for p in self.peers:
                msg = held.get(p)
                if msg is not None and msg.fix and self._relative[p].known is None:
                    self._accumulate_relative(p, msg)
        return WrenchMessage(
            sender=self.index,
            stamp=stamp,
            wrench_grasp=wrench_grasp,
            wrench_world=wrench_world,
            grasp_pos_world=pos_wg,
            grasp_rot_world=rot_wg,
            fix=fix,
            wrench_cov_grasp=sent_cov,
            tainted=tainted,
            **motion,
        )
