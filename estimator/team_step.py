"""One control step of a whole team's estimators in one compiled call.

At each control step, each holding robot's estimator does the common path of ``per_step``
(``estimator_step``: the pre-, rate, product and balance filters' steps, the attitude, the
actuation covariance). ``TeamStep`` does it for every robot of the team that can take that path
in one call of ``team_step``, which runs ``per_step.estimator_step`` on each robot's row: the
same compiled arithmetic as the per-robot call, bit for bit. At an update instant the per-robot
parts around it stay per robot, in ``EstimatorInputs.step``'s order: the servos' ripple map
refreshed before the call, the instant recorded and its message made after it.

The states that step changes in place (``STATE_FIELDS``: the four filters' states and previous
inputs, the actuation covariance sum, the attitude R_WB and p_WB, the servos' ripple map and last
ripple) live in one record of N rows (``records``); each estimator's attributes are views of its
row, so the per-robot path (``EstimatorInputs.step``) and the team call update the same memory.
The per-robot path may rebind an attribute to a new array (a fix on the Python path, the ripple
map's refresh at an update instant; an instant restarts the actuation covariance in place);
after any step a robot took that path its row is checked again (``_bind``): a rebound
attribute is copied into the row and viewed again. The readings a robot's step used
(``EstimatorInputs._last_input``: the accelerometer's, less the servos' ripple, the gyro's, the
joint angles and the thrust command, which the Python path holds when a reading is missing) are
copied into its row too (``LAST_INPUT_FIELDS``) and its ``_last_input`` is the tuple of their
views. Nothing else may step the estimators of a team between its steps.
"""

from __future__ import annotations

import operator

import numpy as np
from numba import njit

from .per_step import NOT_USABLE, estimator_step
from .records import as_interned
from .step_parts import RIPPLE_MOVING, ripple_case

# The per-step states: record field, the estimator's attribute that is a view of it.
STATE_FIELDS = (
    ("pre_state", "pre.filter.state"),
    ("pre_u_prev", "pre.filter._u_prev"),
    ("rate_state", "pre.rate_filter.state"),
    ("rate_u_prev", "pre.rate_filter._u_prev"),
    ("prod_state", "pre.product_filter.state"),
    ("prod_u_prev", "pre.product_filter._u_prev"),
    ("bal_state", "balance_filter.state"),
    ("bal_u_prev", "balance_filter._u_prev"),
    ("act_cov_sum", "_act_cov_sum"),
    ("rot_world_base", "_rot_world_base"),
    ("pos_world_base", "_pos_world_base"),
    ("ripple_map", "_servo_ripple_map"),
    ("ripple_prev", "_servo_ripple_prev"),
)
# The readings the last step used (``EstimatorInputs._last_input``'s order): record fields.
LAST_INPUT_FIELDS = ("last_accel", "last_gyro", "last_q", "last_thrust")
_RIPPLE_MAP = [field for field, _ in STATE_FIELDS].index("ripple_map")
# For each field: the object that holds the attribute, and the attribute's name.
_OWNERS = tuple(
    (operator.attrgetter(path.rpartition(".")[0]) if "." in path else None, path.rpartition(".")[2])
    for _, path in STATE_FIELDS
)


@njit(cache=True)
def team_step(constants, states, ready, has_map, has_imu, accel, gyro, q, thrust, fix_pos,
              fix_quat, has_fix, do_balance, target_rate, outcome, lever) -> None:  # fmt: skip
    """``per_step.estimator_step`` for each robot i ``ready`` with an IMU frame (``has_imu``),
    on row i of the ``constants`` (N,) (``estimator_constants``' rows) and of the ``states``
    (N,) (fields ``STATE_FIELDS`` and ``LAST_INPUT_FIELDS``), with row i of the readings
    (accel, gyro (N, 3) IMU axes; q (N, n_joints) rad; thrust (N, 6) N and N m; the fix
    fix_pos (N, 3) m, fix_quat (N, 4) where has_fix), the servos' ripple taken off with their
    targets' rate ``target_rate`` (N, n_joints) rad/s where the robot ``has_map`` (its row's
    ripple map made). A robot without one whose ripple changes this step (``ripple_case``
    RIPPLE_MOVING) is left to its own path, which makes the map; without one and at rest its
    step is taken without the ripple, as its own path takes it. Writes its outcome and lever (m)
    into ``outcome`` and ``lever`` (N,) (NOT_USABLE and NaN for the other rows) and, for a step
    taken, the readings it used into the row's ``LAST_INPUT_FIELDS``."""
    # The readings' rows go through one buffer of each, contiguous whatever their layout.
    a, g, qi, t = np.empty(3), np.empty(3), np.empty(q.shape[1]), np.empty(6)
    pos, quat, rate = np.empty(3), np.empty(4), np.empty(target_rate.shape[1])
    for i in range(states.shape[0]):
        outcome[i], lever[i] = NOT_USABLE, np.nan
        if not (ready[i] and has_imu[i]):
            continue
        a[:], g[:], qi[:], t[:] = accel[i], gyro[i], q[i], thrust[i]
        pos[:], quat[:], rate[:] = fix_pos[i], fix_quat[i], target_rate[i]
        s = states[i]
        if not has_map[i] and ripple_case(rate, s.ripple_prev[:], qi) == RIPPLE_MOVING:
            continue
        outcome[i], lever[i] = estimator_step(
            constants[i : i + 1], s.pre_state[:], s.pre_u_prev[:], s.rate_state[:],
            s.rate_u_prev[:], s.prod_state[:], s.prod_u_prev[:], s.bal_state[:], s.bal_u_prev[:],
            s.act_cov_sum[:], s.rot_world_base[:], s.pos_world_base[:], a, g, qi, t, pos, quat,
            has_fix[i], do_balance, s.ripple_map[:], rate, s.ripple_prev[:], s.last_accel[:],
            has_map[i],
        )  # fmt: skip
        if outcome[i] != NOT_USABLE:  # the accelerometer's reading used is in last_accel
            s.last_gyro[:], s.last_q[:], s.last_thrust[:] = g, qi, t


class TeamStep:
    """The common path of a team's ``estimators`` (``CargoEstimator``, robot index order) in one
    call per control step (module docstring). The team call is taken only when every estimator
    shares one constants layout and one schedule (else never: ``step`` hands every robot back);
    per robot, only with an IMU frame, its filters started and its attitude known, no fused
    motion, its servos' last ripple known (and its ripple map made, or the ripple at rest), the
    stamp increasing. ``enabled`` False: every robot takes the per-robot path."""

    enabled = True

    def __init__(self, estimators: list) -> None:
        self.estimators = estimators
        self._constants = _stacked_constants(estimators)
        n = len(estimators)
        self._states: np.ndarray | None = None  # the record of the states, made at first use
        self._rows: list[tuple[np.ndarray, ...]] = []  # each robot's views of its row
        self._last_inputs: list[tuple[np.ndarray, ...]] = []  # and of its LAST_INPUT_FIELDS
        self._ready = np.zeros(n, dtype=bool)  # robots whose attributes are their row's views
        self._has_map = np.zeros(n, dtype=bool)  # ready robots whose servo ripple map is made
        self._unchecked = set(range(n))  # robots whose attributes may have been rebound
        self._holding: tuple | None = None
        self._stepping = np.zeros(n, dtype=bool)  # the robots ready and holding
        self._outcome, self._lever = np.empty(n, dtype=np.int64), np.empty(n)  # team_step's
        self._last_k = -1
        self._update_every = estimators[0].update_every if estimators else 1
        self._regressor_every = estimators[0].regressor_every if estimators else 1

    # A copy (deepcopy, pickle) has detached arrays: its rows are made again at its next step.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_states=None, _rows=[], _last_inputs=[])
        state["_unchecked"] = set(range(len(self.estimators)))
        state["_ready"] = np.zeros(len(self.estimators), dtype=bool)
        state["_has_map"] = np.zeros(len(self.estimators), dtype=bool)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self._constants is not None:
            self._constants = as_interned(self._constants)

    def step(self, k: int, holding, readings, commands: np.ndarray,
             arm_rates: np.ndarray) -> tuple[list[int], list[tuple[int, object]]]:  # fmt: skip
        """Control step ``k`` of the robots ``holding`` (indices, increasing) with their
        ``readings`` (``envs.sensors.SensorReadings``' arrays, one row per robot), thrust
        ``commands`` (N, 6) and servo targets' ``arm_rates`` (N, n_joints): the robots that can
        take the team call are stepped in it, as their ``EstimatorInputs.step`` would; at an
        update instant each one's servo ripple map is refreshed first and its instant recorded
        after (``EstimatorInputs.instant_after_compiled_step``). Returns the others, in
        ``holding``'s order, for the per-robot path (and whose reading the compiled step
        refused), and the messages published, (robot, message) in ``holding``'s order."""
        off = self._constants is None or not self.enabled
        if off or k <= self._last_k:
            self._unchecked.update(holding)
            self._last_k = max(self._last_k, k)
            return list(holding), []
        self._last_k = k
        if self._unchecked:
            for i in self._unchecked:
                self._ready[i] = self._bind(i, k)
            self._unchecked.clear()
            self._holding = None
        if self._states is None:  # no robot could take the team call yet
            self._unchecked.update(holding)
            return list(holding), []
        if holding != self._holding:  # the robots ready and holding
            self._holding = tuple(holding)
            self._stepping[:] = False
            self._stepping[list(holding)] = True
            self._stepping &= self._ready
        r, stepping = readings, self._stepping
        instant = k % self._update_every == 0
        if instant:
            stepping = self._refresh_ripple_maps(holding, r, arm_rates)
        do_balance = k % self._regressor_every == 0
        team_step(
            self._constants, self._states, stepping, self._has_map, r.has_imu, r.accel_imu,
            r.gyro_imu, r.joint_pos_rad, commands, r.base_pos_world, r.base_quat_world,
            r.has_fix, do_balance, arm_rates, self._outcome, self._lever,
        )  # fmt: skip
        others = self._after_step(k, holding, do_balance)
        if not instant:
            return others, []
        return others, self._record_instants(k, holding, others, r.joint_pos_rad)

    def _refresh_ripple_maps(self, holding, readings, arm_rates) -> np.ndarray:
        """At an update instant, the servos' ripple map of each robot to step refreshed
        (``EstimatorInputs._refresh_servo_ripple_map``, as its ``step`` does first) into its
        row; returns the robots to step (those whose map is gone are left to their own path).
        A robot without a map yet has none to refresh (its own path makes it: ``team_step``)."""
        stepping = self._stepping.copy()
        q = readings.joint_pos_rad
        for i in holding:
            if not (stepping[i] and self._has_map[i] and readings.has_imu[i]):
                continue
            est = self.estimators[i]
            est._refresh_servo_ripple_map(q[i], arm_rates[i])
            view = self._rows[i][_RIPPLE_MAP]
            value = est._servo_ripple_map
            if value is view:
                continue
            if value is None or value.shape != view.shape:
                stepping[i] = False  # its own path steps it (a refresh there is the same)
                self._unchecked.add(i)
                continue
            view[...] = value
            est._servo_ripple_map = view
        return stepping

    def _record_instants(self, k, holding, others, joint_pos_rad) -> list[tuple[int, object]]:
        """At an update instant, each robot stepped in the team call records its instant
        (``EstimatorInputs.instant_after_compiled_step``, at its joint angles ``joint_pos_rad``
        (N, n_joints)); their messages, (robot, message). Recording restarts the actuation
        covariance in place, so the robot's row needs no check."""
        published = []
        outcomes = self._outcome.tolist()
        for i in holding:
            if i in others:
                continue
            msg = self.estimators[i].instant_after_compiled_step(k, outcomes[i], joint_pos_rad[i])
            if msg is not None:
                published.append((i, msg))
        return published

    def _after_step(self, k, holding, do_balance) -> list[int]:
        """The stamps and counters of the robots stepped
        (``EstimatorInputs._count_compiled_step``; the readings they used are in their rows);
        the others returned."""
        others = []
        outcomes, levers = self._outcome.tolist(), self._lever.tolist()
        for i in holding:
            o = outcomes[i]
            if o == NOT_USABLE:
                others.append(i)
                self._unchecked.add(i)
                continue
            self.estimators[i]._count_compiled_step(k, o, levers[i], do_balance)
        return others

    def _bind(self, i: int, k: int) -> bool:
        """Can robot i take the team call at step ``k``? If so, its attributes are views of its
        row (a rebound one copied in and viewed again); a servo ripple map not made yet stays
        None (``has_map``: ``team_step`` leaves the robot to its own path until it is made)."""
        est = self.estimators[i]
        if est._fused is not None or not est._filters_ready or est.stamp >= k:
            return False
        if est._servo_ripple_prev is None:
            return False
        if self._states is None:
            self._make_rows()
        if not self._bind_last_input(est, self._last_inputs[i]):
            return False
        self._has_map[i] = est._servo_ripple_map is not None
        rebound, fits = False, True
        for (owner_of, name), view in zip(_OWNERS, self._rows[i], strict=True):
            owner = est if owner_of is None else owner_of(est)
            value = getattr(owner, name)
            if value is view or (value is None and name == "_servo_ripple_map"):
                continue
            if np.shape(value) != view.shape:
                fits = False
                break
            view[...] = value
            setattr(owner, name, view)
            rebound = True
        if rebound:  # the filters' states may be new views: the compiled step's tuple of them
            est._step_states = est._filter_states()
        return fits

    @staticmethod
    def _bind_last_input(est, views: tuple[np.ndarray, ...]) -> bool:
        """``est._last_input`` made ``views`` (its row's ``LAST_INPUT_FIELDS``), its readings
        copied in; False (nothing changed) when it has none or of other shapes."""
        last = est._last_input
        if last is views:
            return True
        if last is None or any(np.shape(x) != v.shape for x, v in zip(last, views, strict=True)):
            return False
        for view, value in zip(views, last, strict=True):
            view[...] = value
        est._last_input = views
        return True

    def _make_rows(self) -> None:
        """The states' record (fields ``STATE_FIELDS`` and ``LAST_INPUT_FIELDS``, shapes of the
        first estimator's) and each robot's views of its row."""
        est = self.estimators[0]
        nj = est.robot.n_joints
        shapes = {
            "act_cov_sum": (6, 6), "rot_world_base": (3, 3), "pos_world_base": (3,),
            "ripple_map": (3, nj), "ripple_prev": (3,), "last_accel": (3,), "last_gyro": (3,),
            "last_q": (nj,), "last_thrust": (6,),
        }  # fmt: skip
        fields = []
        for (field, _), (owner_of, name) in zip(STATE_FIELDS, _OWNERS, strict=True):
            shape = shapes.get(field) or getattr(owner_of(est), name).shape
            fields.append((field, np.float64, shape))
        fields += [(field, np.float64, shapes[field]) for field in LAST_INPUT_FIELDS]
        self._states = as_interned(np.zeros(len(self.estimators), dtype=np.dtype(fields)))
        n = len(self.estimators)
        self._rows = [tuple(self._states[field][i] for field, _ in STATE_FIELDS) for i in range(n)]
        self._last_inputs = [
            tuple(self._states[field][i] for field in LAST_INPUT_FIELDS) for i in range(n)
        ]


def _stacked_constants(estimators: list) -> np.ndarray | None:
    """The estimators' constants records (``estimator_constants``) as one (N,) record, or None
    when their layouts or schedules differ (or there are none)."""
    if not estimators:
        return None
    first = estimators[0]
    for est in estimators:
        if est._step_constants.dtype is not first._step_constants.dtype:
            return None
        if (est.update_every, est.regressor_every) != (first.update_every, first.regressor_every):
            return None
    return as_interned(np.concatenate([est._step_constants for est in estimators]))
