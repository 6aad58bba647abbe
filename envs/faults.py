"""Injected faults (the env docstring's section Faults) and scheduled releases: their specs,
validated, and the control steps they act at."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from astrocargo.envs.comms import FAULT_STATS
from astrocargo.envs.validation import check_finite_number

FAULT_KINDS: dict[str, tuple[str, ...]] = {  # kind -> its own optional fields
    "imu_dropout": ("prob",),
    "localization_outage": (),
    "propulsion": ("scale",),
    "comm_burst": ("prob",),
    "comm_delay": ("delay_s",),
}
# infos[agent]["faults"]: counted by the env, and by the channel (copies, comms.FAULT_STATS).
FAULT_COUNTERS = ("imu_frames_missing", "fixes_missing", "propulsion_steps")
NO_FAULT_COUNTS = dict.fromkeys(FAULT_COUNTERS + tuple(f"messages_{k}" for k in FAULT_STATS), 0)


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
        start = check_finite_number("fault start_s", spec["start_s"], "a finite number >= 0 s")
        duration = check_finite_number(
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
            value = check_finite_number(f"fault {key}", spec[key], f"a number in ({low}, {high}]")
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


def parse_faults(faults: Any, n_robots: int) -> tuple[Fault, ...]:
    """``faults`` (None or a list of dicts or ``Fault``s) as validated ``Fault``s."""
    if faults is None:
        return ()
    if isinstance(faults, dict | Fault) or not isinstance(faults, list | tuple):
        raise ValueError(f"faults must be None or a list of dicts (or Faults), got {faults!r}")
    return tuple(Fault.parse(f, n_robots) for f in faults)


def parse_release_at(release_at: Any, n_robots: int, dt_s: float) -> dict[int, int]:
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
        time_s = check_finite_number("release_at time_s", time_s, "a finite number >= 0 s")
        if time_s < 0:
            raise ValueError(f"release_at time_s must be a finite number >= 0 s, got {time_s}")
        # The first control instant k * dt at or after time_s (k >= 1: never at reset).
        steps[int(robot)] = max(1, math.ceil(time_s / dt_s - 1e-9))
    return steps


class FaultSchedule:
    """An episode's faults at the control steps they act at, and what they did: per robot,
    the counters ``FAULT_COUNTERS`` (episode totals). ``rng``: the faults' own generator (None
    without faults, so that a run without them draws as it always did)."""

    def __init__(self, faults: tuple[Fault, ...], dt_s: float, n_robots: int) -> None:
        # Each fault with the control steps [first, end) it is active at.
        self.windows = [(f, *f.steps(dt_s)) for f in faults]
        self.n_robots = n_robots
        self.rng: np.random.Generator | None = None
        self.counts = {k: np.zeros(n_robots, dtype=np.int64) for k in FAULT_COUNTERS}

    def reset(self, rng: np.random.Generator | None, channel: Any) -> None:
        """Start an episode: counters to zero, the channel's bursts and delays scheduled."""
        self.rng = rng
        self.counts = {k: np.zeros(self.n_robots, dtype=np.int64) for k in FAULT_COUNTERS}
        for fault, first, end in self.windows:
            if fault.kind == "comm_burst":
                channel.add_burst(fault.robot, first, end, fault.prob)
            elif fault.kind == "comm_delay":
                channel.add_delay(fault.robot, first, end, fault.delay_s)

    def active(self, kind: str, k: int) -> list[Fault]:
        """The faults of ``kind`` active at control step ``k``."""
        return [f for f, first, end in self.windows if f.kind == kind and first <= k < end]

    def thrust_scale(self, k: int, holding: tuple[int, ...], unit: np.ndarray) -> np.ndarray:
        """Delivered over commanded thrust (H,) of the ``holding`` robots at step ``k``: the
        propulsion faults' scales (``unit``, ones, without any); the steps are counted."""
        if not self.windows:
            return unit
        scale = unit.copy()
        weakened = set()
        for fault in self.active("propulsion", k):
            if fault.robot in holding:
                scale[holding.index(fault.robot)] *= fault.scale
                weakened.add(fault.robot)
        if weakened:
            self.counts["propulsion_steps"][list(weakened)] += 1
        return scale

    def apply_to_readings(self, has_imu: np.ndarray, has_fix: np.ndarray, k: int) -> None:
        """Clear (in place) the IMU frames and fixes that the faults of step ``k`` take away
        (counted); an IMU dropout with ``prob`` < 1 draws from ``rng``."""
        if not self.windows:
            return
        for fault in self.active("imu_dropout", k):
            i = fault.robot
            if not has_imu[i]:
                continue  # let go, or two overlapping dropouts
            if fault.prob < 1.0 and self.rng.random() >= fault.prob:
                continue
            has_imu[i] = False
            self.counts["imu_frames_missing"][i] += 1
        for fault in self.active("localization_outage", k):
            i = fault.robot
            if has_fix[i]:
                has_fix[i] = False
                self.counts["fixes_missing"][i] += 1

    def infos(self, k: int, channel_stats: dict[str, np.ndarray]) -> list[dict[str, Any]]:
        """Every robot's counters (with the channel's ``channel_stats`` as messages_<name>)
        and the kinds of its faults active at step ``k``."""
        if not self.windows:  # none injected: every counter stays 0
            return [_no_fault_info() for _ in range(self.n_robots)]
        counts = {name: v.tolist() for name, v in self.counts.items()}
        counts.update({f"messages_{name}": v.tolist() for name, v in channel_stats.items()})
        active: list[list[str]] = [[] for _ in range(self.n_robots)]
        for f, first, end in self.windows:
            if first <= k < end:
                active[f.robot].append(f.kind)
        return [
            {**{name: c[i] for name, c in counts.items()}, "active": active[i]}
            for i in range(self.n_robots)
        ]


def _no_fault_info() -> dict[str, Any]:
    """A robot's new faults info while no fault is injected: every counter 0, none active (a
    copy of the counters' dict, then the list: cheaper than ``dict(..., active=[])``)."""
    info = NO_FAULT_COUNTS.copy()
    info["active"] = []
    return info
