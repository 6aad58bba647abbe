"""The team's estimation inside the env: one ``CargoEstimator`` per robot and the messages
between them (``TeamEstimation``, held by ``CargoTransport``).

Per control step (``step``): each robot holding the cargo feeds its own estimator its sensor
packet and its thrust command; the messages it publishes go into the communication channel; what
the channel delivers is handed to the receivers' estimators; each estimator then updates with its
complete instants. After an update the estimates are gathered (``refresh``): means and standard
deviations of pi (10,) per robot, in each robot's grasp frame (kg, kg m, kg m^2), their errors
against the true cargo, and the sum of the log standard deviations (the information reward).

The latest message each robot has received from each peer is also kept as arrays, row receiver,
column sender: its wrench on the cargo (world axes, N and N m), its stamp (control steps; -1:
none) and the sender's arm angles and rates when it sent it (rad, rad/s): the observations' peer
slots read them (``peer_slot_values``).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from astrocargo.envs.comms import freeze_arrays
from astrocargo.envs.sensors import SensorReadings
from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.inertia import errors_given_true, true_principal_moments
from astrocargo.estimator.rne import RobotDescription
from astrocargo.estimator.team_step import TeamStep

SENT_ARM_KEPT = 1000  # messages' arm states kept per sender (160 s at one per 10 steps)
LOG_STD_FLOOR = 1e-12


def make_estimators(
    robots: list[RobotDescription],
    dt_s: float,
    estimator_kwargs: dict[str, Any],
    relative_grasp,
) -> list[CargoEstimator]:
    """One estimator per robot, each with every other robot as a peer. The grasp layout
    (``relative_grasp(i, j)``: robot j's grasp frame in robot i's, rotation and position m) is
    known geometry, like the handrail poses the observations use; estimating it from fixes
    biases early updates. A bad keyword in ``estimator_kwargs`` raises ValueError."""
    n = len(robots)
    out = []
    for i in range(n):
        peers = [j for j in range(n) if j != i]
        kwargs = {"relative_grasps": {j: relative_grasp(i, j) for j in peers}, **estimator_kwargs}
        try:
            out.append(CargoEstimator(robots[i], i, peers, dt_s, **kwargs))
        except TypeError as err:
            raise ValueError(f"bad estimator_kwargs {estimator_kwargs!r}: {err}") from err
    return out


class FreshEstimators:
    """``make_estimators`` for every episode, cheaper: the estimators for the grasp layout
    ``relative_grasp(i, j)`` (the world's handrails, fixed for the env's life: read once here)
    are built at the first call and kept unstepped; each call returns a copy of them
    (``copy.deepcopy``, sharing the ``robots`` descriptions as built ones do), which starts in
    the same state as newly built ones."""

    def __init__(
        self,
        robots: list[RobotDescription],
        dt_s: float,
        estimator_kwargs: dict[str, Any],
        relative_grasp: Callable,
    ) -> None:
        self.robots, self.dt_s, self.estimator_kwargs = robots, dt_s, estimator_kwargs
        n = len(robots)
        self.grasps = {(i, j): relative_grasp(i, j) for i in range(n) for j in range(n) if i != j}
        self._built: list[CargoEstimator] | None = None

    def __call__(self) -> list[CargoEstimator]:
        """Fresh estimators (``make_estimators`` for the grasp layout)."""
        if self._built is None:
            self._built = make_estimators(
                self.robots, self.dt_s, self.estimator_kwargs, lambda i, j: self.grasps[i, j]
            )
        return copy.deepcopy(self._built, {id(r): r for r in self.robots})


@njit(cache=True)
def message_ages(stamp, valid, step_count, dt_s, age) -> None:
    """The age of each slot's latest message, s, into ``age``: (k - stamp) dt where ``valid``,
    else 0, for stamps (int, control steps), ``valid`` (bool) and ``age`` (float) of one shape,
    at control step k = ``step_count`` of period ``dt_s``."""
    for idx in np.ndindex(stamp.shape):
        age[idx] = (step_count - stamp[idx]) * dt_s if valid[idx] else 0.0


@njit(cache=True)
def log_std_sums(std, floor, out) -> None:
    """Into ``out`` (N,): sum_k log(max(std[i, k], floor)) of standard deviations (N, K)."""
    for i in range(std.shape[0]):
        total = 0.0
        for k in range(std.shape[1]):
            total += np.log(max(std[i, k], floor))
        out[i] = total


class TeamEstimation:
    """Every robot's estimator and the messages between them for one episode (module
    docstring) of ``n_robots``. ``estimators`` is the list of ``CargoEstimator`` (robot index
    order; empty: no estimation, the peer slots stay zero); ``peer_msgs[i]`` maps a sender to
    the latest message robot i received from it."""

    def __init__(self, n_robots: int, estimators: list[CargoEstimator],
                 true_params_grasp: list[np.ndarray], dt_s: float) -> None:  # fmt: skip
        n = n_robots
        self.estimators = estimators
        self.dt_s = dt_s
        self.true_params_grasp = np.array(true_params_grasp, dtype=float)
        self._true_moments: np.ndarray | None = None  # their principal moments (``refresh``)
        self.sent_arm: list[dict[int, np.ndarray]] = [{} for _ in range(n)]
        self.peer_msgs: list[dict[int, Any]] = [{} for _ in range(n)]
        self.latest_wrench = np.zeros((n, n, 6))  # [receiver, sender], world axes
        self.latest_stamp = np.full((n, n), -1, dtype=np.int64)
        self.latest_arm = np.zeros((n, n, 4))
        # Per robot: the peer in each of its peer slots (increasing index, skipping itself).
        slots = [[j for j in range(n) if j != i] for i in range(n)]
        self.peer_slots = np.array(slots, dtype=np.int64).reshape(n, n - 1)
        # `peer_slot_values` apart from the ages, while no message and no ``acting`` changes them.
        self._slot_cache: tuple[bytes, tuple[np.ndarray, ...]] | None = None
        self._slot_ages = np.zeros((n, n - 1))  # `peer_slot_values`' ages, rewritten per call
        self._team_step = TeamStep(estimators)  # the common path of every robot in one call
        # The robots that held at the last ``process`` of all of them, and the last step through
        # which all their ``process`` return 0 while nothing reaches them (``_process``).
        self._quiet: tuple[tuple, float] = ((), -math.inf)

    def step(self, readings: SensorReadings, commands: np.ndarray, k: int, holding,
             arm_rates: np.ndarray, channel) -> bool:  # fmt: skip
        """Control step ``k``: the ``holding`` robots' estimators ingest their packets and
        commands (n_robots, 6); messages are sent (with the sender's arm angles and
        ``arm_rates``) and delivered through ``channel``; every estimator processes its
        complete instants. Returns whether any estimate changed."""
        estimators = self.estimators
        # The robots that can go through the team's compiled call, in it; the others one by one.
        others, published = self._team_step.step(k, holding, readings, commands, arm_rates)
        if others:
            published += self._step_each(others, readings, commands, k, arm_rates)
            published.sort(key=lambda sent: sent[0])  # sent in robot order, as stepped alone
        for i, msg in published:
            self._send(i, msg, readings.joint_pos_rad[i], arm_rates[i], channel, k)
        delivered = channel.due(k)
        if delivered:
            for receiver, msgs in channel.deliver(k).items():
                for msg in msgs:
                    estimators[receiver].receive(msg)
                self._keep_latest(receiver, msgs)
        return self._process(k, holding, reached=bool(others or published) or delivered)

    def _process(self, k: int, holding, reached: bool) -> bool:
        """``process`` of every ``holding`` estimator at step ``k``; whether any estimate
        changed. Not called when it would change nothing: when no robot took its own step nor
        received (not ``reached``: each one's stamp alone changed, in the team's call), the
        robots are those of the last call and ``k`` is within the steps through which all of
        them stay quiet (``EstimatorInputs.quiet_through``, asked after that call)."""
        held, quiet_until = self._quiet
        if not reached and k <= quiet_until and holding == held:
            return False
        estimators, updated = self.estimators, False
        for i in holding:
            updated |= estimators[i].process() > 0
        quiet = min((estimators[i].quiet_through() for i in holding), default=-math.inf)
        self._quiet = (tuple(holding), quiet)
        return updated

    def _step_each(self, robots, readings: SensorReadings, commands: np.ndarray, k: int,
                   arm_rates: np.ndarray) -> list[tuple[int, Any]]:  # fmt: skip
        """``CargoEstimator.step`` of each of ``robots`` in turn; the messages they publish,
        (robot, message)."""
        r = readings  # row i of its arrays, None for a missing IMU frame or fix (``packet``)
        has_imu, has_fix, estimators = r.has_imu.tolist(), r.has_fix.tolist(), self.estimators
        published = []
        for i in robots:
            imu, fix = has_imu[i], has_fix[i]
            msg = estimators[i].step(
                k, r.accel_imu[i] if imu else None, r.gyro_imu[i] if imu else None,
                r.joint_pos_rad[i], commands[i], r.base_pos_world[i] if fix else None,
                r.base_quat_world[i] if fix else None, servo_target_rate=arm_rates[i],
            )  # fmt: skip
            if msg is not None:
                published.append((i, msg))
        return published

    def _send(self, i: int, msg, q: np.ndarray, arm_rate: np.ndarray, channel, k: int) -> None:
        """Robot i's message ``msg`` into ``channel`` at step k; its arm angles ``q`` and
        rates kept for the peer slots."""
        sent = self.sent_arm[i]
        sent[msg.stamp] = np.concatenate((q, arm_rate))
        if len(sent) > SENT_ARM_KEPT:
            del sent[next(iter(sent))]  # the oldest
        channel.send(freeze_arrays(msg), k)  # its receivers share it

    def _keep_latest(self, receiver: int, msgs: list) -> None:
        """Keep each of ``msgs``, in turn, as the latest one ``receiver`` has from its sender,
        if it is newer."""
        kept, stamps = self.peer_msgs[receiver], self.latest_stamp[receiver]
        wrenches, arms = self.latest_wrench[receiver], self.latest_arm[receiver]
        for msg in msgs:
            j = msg.sender
            if msg.stamp > stamps[j]:
                self._slot_cache = None
                kept[j] = msg
                stamps[j] = msg.stamp
                wrenches[j] = msg.wrench_world
                arm = self.sent_arm[j].get(msg.stamp)
                arms[j] = 0.0 if arm is None else arm

    def forget(self, receiver: int, sender: int) -> None:
        """``receiver`` no longer counts messages from ``sender`` (it let go of the cargo)."""
        self._slot_cache = None
        self._quiet = ((), -math.inf)  # the peers change: every holding robot processes
        self.peer_msgs[receiver].pop(sender, None)
        self.latest_stamp[receiver, sender] = -1
        self.latest_wrench[receiver, sender] = 0.0
        self.latest_arm[receiver, sender] = 0.0

    def refresh(self) -> tuple[np.ndarray, np.ndarray, list[dict[str, float]]]:
        """Every estimator's mean and standard deviation of pi, (n_robots, 10), row i robot i's
        (``CargoEstimator.params_mean``, ``params_std``), and its errors against the true
        cargo (mass relative, centre of mass m, principal moments relative); also updates
        ``log_std_sums``. The arrays are new at each call; the rows are filled in place."""
        n = len(self.estimators)
        est_mean, est_std = np.empty((n, 10)), np.empty((n, 10))
        for i, est in enumerate(self.estimators):
            est_mean[i] = est.params_mean()
            est.params_std(est_std[i])
        if self._true_moments is None:  # the true cargo's principal moments, checked once
            self._true_moments = true_principal_moments(self.true_params_grasp)
        out = np.empty((n, 5))  # mass, com, principal (3)
        errors_given_true(est_mean, self.true_params_grasp, self._true_moments, out)
        self.log_std_sums = np.empty(n)
        log_std_sums(est_std, LOG_STD_FLOOR, self.log_std_sums)
        errors = [
            {"mass_rel_err": row[0], "com_err_m": row[1], "principal_rel_err": row[2:]}
            for row in out.tolist()
        ]
        return est_mean, est_std, errors

    def peer_slot_values(self, acting: np.ndarray, step_count: int) -> tuple[np.ndarray, ...]:
        """Each robot's peer slots: the latest message's wrench (world axes) (N, P, 6), its age
        in s and whether one has arrived (N, P), the sender's arm angles and rates when it sent
        it (N, P, 4); zeros before the first message and in the rows of robots not ``acting``
        (bool (N,)). The wrench, arrival and arm arrays are read-only: they are kept until a
        message or ``acting`` changes them. The ages' array is rewritten at the next call."""
        acting_key = np.asarray(acting, dtype=bool).tobytes()
        if self._slot_cache is None or self._slot_cache[0] != acting_key:
            self._slot_cache = (acting_key, self._slot_arrays(acting))
        stamp, valid, wrench, arrived, arm = self._slot_cache[1]
        message_ages(stamp, valid, step_count, self.dt_s, self._slot_ages)
        return wrench, self._slot_ages, arrived, arm

    def _slot_arrays(self, acting: np.ndarray) -> tuple[np.ndarray, ...]:
        """`peer_slot_values`' stamps, validity, wrenches, arrivals and arm states (read-only),
        new arrays filled by one compiled call (``slot_arrays``)."""
        n, p = self.peer_slots.shape
        stamp, valid = np.empty((n, p), dtype=np.int64), np.empty((n, p), dtype=bool)
        wrench, arrived, arm = np.empty((n, p, 6)), np.empty((n, p)), np.empty((n, p, 4))
        arrays = (stamp, valid, wrench, arrived, arm)
        slot_arrays(
            self.latest_stamp, self.latest_wrench, self.latest_arm, self.peer_slots,
            np.asarray(acting, dtype=bool), *arrays,
        )  # fmt: skip
        for array in arrays:
            array.flags.writeable = False
        return arrays


@njit(cache=True)
def slot_arrays(latest_stamp, latest_wrench, latest_arm, peer_slots, acting, stamp, valid,
                wrench, arrived, arm) -> None:  # fmt: skip
    """The peer slots (N, P) from the latest messages [receiver, sender]: robot i's slot s holds
    sender j = ``peer_slots[i, s]``: ``stamp`` its stamp, ``valid`` stamp >= 0 and
    ``acting[i]``, ``arrived`` valid as 0/1, ``wrench`` (N, P, 6) and ``arm`` (N, P, 4) its
    wrench and arm state where valid, else zeros."""
    for i in range(peer_slots.shape[0]):
        for s in range(peer_slots.shape[1]):
            j = peer_slots[i, s]
            stamp[i, s] = latest_stamp[i, j]
            ok = stamp[i, s] >= 0 and acting[i]
            valid[i, s] = ok
            arrived[i, s] = 1.0 if ok else 0.0
            for c in range(6):
                wrench[i, s, c] = latest_wrench[i, j, c] if ok else 0.0
            for c in range(4):
                arm[i, s, c] = latest_arm[i, j, c] if ok else 0.0
