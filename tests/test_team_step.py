"""The team's one compiled call per control step (``estimator.team_step``) leaves every
estimator exactly as the per-robot path does (issue #14, item 5)."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

import astrocargo.estimator.team_step as team_step_module
from astrocargo.envs.transport import CargoTransport
from astrocargo.estimator.cargo_estimator import CargoEstimator


def _actions(n: int, k: int, arms_from: dict[int, float] | None = None) -> np.ndarray:
    """Every robot's thrust and arm actions; with ``arms_from``, robot i's arm actions are zero
    (its arm stays deployed: the servos' ripple at rest) before step ``arms_from[i]``."""
    phase = np.arange(8) + 3.0 * np.arange(n)[:, None]
    actions = 0.3 * np.sin(0.05 * k + phase)
    for i, first in (arms_from or {}).items():
        if k < first:
            actions[i, 6:] = 0.0
    return actions


# Faults put into the readings before the estimators see them: step -> (robot, what).
FAULTS = {
    300: (0, "no_imu"),
    333: (1, "nan_accel"),
    341: (0, "nan_gyro"),
    350: (0, "nan_accel"),  # at an update instant: refused by the team call after its refresh
    360: (1, "no_fix"),
    380: (1, "no_fix"),
    401: (0, "no_imu"),
}


def _with_faults(sim: CargoTransport) -> None:
    """Wrap the env's ``TeamEstimation.step`` so that the readings carry ``FAULTS``."""
    estimation = sim.estimation
    step = estimation.step

    def faulty(readings, commands, k, holding, arm_rates, channel):
        robot, what = FAULTS.get(k, (None, None))
        if robot is not None and robot in holding:
            if what == "no_imu":
                readings.has_imu[robot] = False
            elif what == "nan_accel":
                readings.accel_imu[robot, 1] = np.nan
            elif what == "nan_gyro":
                readings.gyro_imu[robot, 2] = np.nan
            elif what == "no_fix":
                readings.has_fix[robot] = False
        return step(readings, commands, k, holding, arm_rates, channel)

    estimation.step = faulty


FILTERS = ("filter", "rate_filter", "product_filter")


def _estimator_arrays(est) -> dict[str, object]:
    """What a control step changes in an estimator: the filters, the attitude, the actuation
    covariance, the servos' ripple, the counters and the filter's estimate."""
    out = {
        f"{f}.{a}": getattr(getattr(est.pre, f), a) for f in FILTERS for a in ("state", "_u_prev")
    }
    out["bal.state"], out["bal.u_prev"] = est.balance_filter.state, est.balance_filter._u_prev
    for name in ("_act_cov_sum", "_rot_world_base", "_pos_world_base", "_servo_ripple_map",
                 "_servo_ripple_prev", "_grasp_lever", "_act_cov_n", "stamp", "n_fixes",
                 "n_bad_readings", "n_missing_imu", "_tainted_until"):  # fmt: skip
        out[name] = getattr(est, name)
    out["last_input"] = est._last_input
    out["x"], out["P"] = est.ukf.x, est.ukf._P
    out["counters"] = est.counters
    return out


def _assert_same(a, b, where) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], (where, key))
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y, where)
    elif a is None or b is None:
        assert a is None and b is None, where
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(where))


@pytest.fixture
def team_calls(monkeypatch):
    """The number of robots each call of the team kernel stepped."""
    stepped_counts: list[int] = []
    kernel = team_step_module.team_step

    def counted(constants, states, stepped, *args):
        stepped_counts.append(int(stepped.sum()))
        return kernel(constants, states, stepped, *args)

    monkeypatch.setattr(team_step_module, "team_step", counted)
    return stepped_counts


@pytest.fixture
def processed(monkeypatch):
    """The estimators whose ``process`` ran, one entry per call."""
    calls: list[CargoEstimator] = []
    process = CargoEstimator.process

    def counted(self):
        calls.append(self)
        return process(self)

    monkeypatch.setattr(CargoEstimator, "process", counted)
    return calls


# A late, lossy channel and a short history: instants wait for lost messages and expire.
LOSSY = {"comm_latency": 0.05, "comm_drop": 0.5, "estimator_kwargs": {"history_s": 0.5}}


# Robot 0's arm starts to move at step 250 (within the faults, off an update instant), robot 1's
# never: until then neither has a servo ripple map.
ARMS_FROM = {0: 253, 1: np.inf}


@pytest.mark.parametrize(
    "n_robots, release_at, channel, arms_from",
    [(2, None, {}, None), (3, [(2, 6.5)], {}, None), (2, None, LOSSY, None),
     (2, None, {}, ARMS_FROM)],
    ids=["2-robots", "3-robots-one-lets-go", "2-robots-lossy", "2-robots-arms-at-rest"],
)  # fmt: skip
def test_team_call_equals_the_per_robot_path(n_robots, release_at, channel, arms_from,
                                             team_calls, processed):  # fmt: skip
    kwargs = {"n_robots": n_robots, "noise": "nominal", "release_at": release_at, **channel}
    team, alone = CargoTransport(**kwargs), CargoTransport(**kwargs)
    for sim in (team, alone):
        sim.reset(np.random.default_rng(5))
        _with_faults(sim)
    alone.estimation._team_step.enabled = False
    released, robot_steps = False, 0
    for k in range(460):
        actions = _actions(n_robots, k, arms_from)
        robot_steps += len(alone.holding)
        results = [sim.step(actions) for sim in (team, alone)]
        released |= bool(results[0].released)
        np.testing.assert_array_equal(
            results[0].observations, results[1].observations, err_msg=str(k)
        )
        for i, (a, b) in enumerate(zip(team.estimators, alone.estimators, strict=True)):
            _assert_same(_estimator_arrays(a), _estimator_arrays(b), (k, i))
        np.testing.assert_array_equal(team.state(), alone.state())
    # The team call stepped robots on most steps, the per-robot path took the faults.
    # Every step once the filters run, update instants included (46 of the 460 steps).
    assert len(team_calls) > 450 and sum(c == n_robots for c in team_calls) > 250
    assert team.estimators[0].n_missing_imu == 2
    assert team.estimators[1].n_bad_readings >= 1
    assert released == (release_at is not None)
    if release_at is not None:
        assert max(team_calls[-20:]) == n_robots - 1
    # The per-robot path processed every holding robot at every step; the team, with the same
    # estimates, only on the steps where something reached its robots or fell out of the history.
    team_processed = sum(any(e is t for t in team.estimators) for e in processed)
    assert len(processed) - team_processed >= robot_steps
    assert 0 < team_processed < robot_steps / 2
    if channel:  # instants expired: on steps where nothing reached the robots
        assert min(est.n_skipped_missing for est in team.estimators) > 0
    if arms_from:  # the team call stepped both robots before either had a ripple map
        maps = [est._servo_ripple_map is not None for est in team.estimators]
        assert maps == [True, False]
        assert sum(c == n_robots for c in team_calls[100:240]) == 140


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
def test_a_copied_team_steps_its_own_estimators(how):
    sim = CargoTransport(n_robots=2, noise="nominal")
    sim.reset(np.random.default_rng(3))
    for k in range(120):
        sim.step(_actions(2, k))
    twin = copy.deepcopy(sim) if how == "deepcopy" else pickle.loads(pickle.dumps(sim))
    for k in range(120, 200):
        sim.step(_actions(2, k))
        twin.step(_actions(2, k))
        np.testing.assert_array_equal(sim.state(), twin.state())
        for a, b in zip(sim.estimators, twin.estimators, strict=True):
            _assert_same(_estimator_arrays(a), _estimator_arrays(b), k)
            assert not np.shares_memory(a.pre.filter.state, b.pre.filter.state)
    # The twin's estimators are bound to the twin's team, not to the original's.
    rows = twin.estimation._team_step._states
    assert rows is not None and np.shares_memory(rows, twin.estimators[1].balance_filter.state)
