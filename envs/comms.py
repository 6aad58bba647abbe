"""The robots' communication channel: latency, message loss and additive wrench noise.

Every message a robot publishes goes to every other robot. Per message and per receiver the
channel decides, at send time, whether the copy is lost (probability ``drop_prob``) and draws the
additive Gaussian noise on its wrench; a kept copy arrives ``latency_steps`` control periods
after it was sent (``latency_s`` rounded to the nearest whole period, halves up: a control loop
reads its mailbox once per period). Each receiver gets its own copy (arrays copied), so one
receiver cannot alter what another one sees; a message whose arrays are all read-only
(``freeze_arrays``) cannot be altered, so the receivers share it (with noise: each gets its own
noisy wrenches and shares the other arrays).

Noise: a wrench [force N; moment N m] drawn with standard deviations ``noise_std`` =
(force, moment) per axis in the sender's grasp frame is added to ``wrench_grasp``; the same
perturbation, rotated with the message's ``grasp_rot_world``, is added to ``wrench_world``, so the
two fields keep describing one wrench (isotropic noise has the same law in either frame).

All randomness comes from the ``np.random.Generator`` given to the constructor, drawn in a fixed
order (per message: receivers in increasing index, drop then noise), so a seeded channel is
reproducible.

Faults (``add_burst``, ``add_delay``), each over a window of control steps [first, end):

- a burst of loss on robot r: every copy sent by r or addressed to r in the window is lost (each
  with probability ``prob``, drawn from the separate ``fault_rng``);
- a delay of robot r's messages: a copy sent by r in the window arrives ``delay_s`` (rounded to
  whole periods, as the latency) later than the usual latency.

A robot that lets go of the cargo leaves the channel (``disconnect``): the copies in flight from
or to it are discarded (counted in ``discarded``), later copies are not addressed to it
(no draws are made for it), and it may send nothing more.

The ordinary loss and noise draws happen first, exactly as without the fault, so a faulty channel
and a healthy one seeded alike agree on every copy the fault does not touch. What the faults did
is counted per robot in ``fault_stats`` (``lost_sent``, ``lost_received``, ``delayed_sent``,
``delayed_received``: copies), apart from ``stats``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections import defaultdict
from dataclasses import dataclass
from typing import Any

import numpy as np

WRENCH_FIELDS = ("wrench_grasp", "wrench_world")


FAULT_STATS = ("lost_sent", "lost_received", "delayed_sent", "delayed_received")


@dataclass(frozen=True)
class _LinkFault:
    robot: int
    first_step: int
    end_step: int  # exclusive
    prob: float = 1.0  # burst: probability that one copy is lost
    extra_steps: int = 0  # delay

    def active(self, step: int) -> bool:
        return self.first_step <= step < self.end_step


def _is_number(value: Any) -> bool:
    """A real number, not a boolean (True would read as 1 s or probability 1)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def _periods(seconds: float, dt_s: float) -> int:
    """Nearest whole number of control periods, halves up (round() takes halves to even: 0.2 s
    at 16 ms would be 12 periods); the tiny margin absorbs float error in seconds / dt."""
    return int(np.floor(seconds / dt_s + 0.5 + 1e-9))


@functools.cache
def _init_fields(cls: type) -> tuple[str, ...]:
    """The names of the dataclass ``cls``'s fields that ``__init__`` takes (those
    ``dataclasses.replace`` passes on), looked up once per class."""
    return tuple(f.name for f in dataclasses.fields(cls) if f.init)


def freeze_arrays(message: Any) -> Any:
    """``message`` with its array fields made read-only (in place; returned), so that the
    channel hands it to its receivers without copies. Its sender must not change them through
    another reference afterwards."""
    for name in _init_fields(type(message)):
        value = getattr(message, name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return message


def _is_frozen(message: Any) -> bool:
    """Whether none of ``message``'s array fields is writable (``freeze_arrays``)."""
    for name in _init_fields(type(message)):
        value = getattr(message, name)
        if isinstance(value, np.ndarray) and value.flags.writeable:
            return False
    return True


class CommChannel:
    """Delivers the robots' messages with latency, loss and noise.

    Args:
        n_robots: robots on the channel; messages carry a ``sender`` index in ``0..n_robots-1``.
        latency_s: delay of every message in seconds, rounded to whole control periods (>= 0).
        drop_prob: probability in [0, 1] that one copy (one message to one receiver) is lost.
        noise_std: (force N, moment N m) standard deviation of the additive wrench noise per axis.
        dt_s: control period in seconds.
        rng: the generator every random draw of loss and noise comes from.
        fault_rng: the generator of the faults' draws (needed by a burst with ``prob`` < 1).
    """

    def __init__(
        self,
        n_robots: int,
        latency_s: float,
        drop_prob: float,
        noise_std: tuple[float, float],
        dt_s: float,
        rng: np.random.Generator,
        fault_rng: np.random.Generator | None = None,
    ) -> None:
        if isinstance(n_robots, bool) or not isinstance(n_robots, int | np.integer):
            raise ValueError(f"n_robots must be a positive integer, got {n_robots!r}")
        if n_robots < 1:
            raise ValueError(f"n_robots must be a positive integer, got {n_robots}")
        if not (_is_number(dt_s) and np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive finite number of seconds, got {dt_s!r}")
        if not (_is_number(latency_s) and np.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"latency_s must be a finite number >= 0 s, got {latency_s!r}")
        if not (_is_number(drop_prob) and 0.0 <= drop_prob <= 1.0):
            raise ValueError(f"drop_prob must be a probability in [0, 1], got {drop_prob!r}")
        noise = np.asarray(noise_std, dtype=float)
        if noise.shape != (2,) or not np.all(np.isfinite(noise)) or np.any(noise < 0):
            raise ValueError(
                f"noise_std must be two finite numbers >= 0 (force N, moment N m), "
                f"got {noise_std!r}"
            )
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        if fault_rng is not None and not isinstance(fault_rng, np.random.Generator):
            raise ValueError(
                f"fault_rng must be None or a Generator, got {type(fault_rng).__name__}"
            )
        self.n_robots = int(n_robots)
        self.dt_s = float(dt_s)
        self.latency_s = float(latency_s)
        self.latency_steps = _periods(self.latency_s, self.dt_s)
        self.drop_prob = float(drop_prob)
        self.noise_std = noise
        self._wrench_noise_std = np.repeat(noise, 3)  # per axis of [force; moment]
        self._noisy = bool(np.any(noise > 0))
        self.rng = rng
        self._queue: dict[int, list[tuple[int, Any]]] = defaultdict(list)  # due step -> copies
        self.stats = {"sent": 0, "delivered": 0, "dropped": 0, "in_flight": 0}
        self.disconnected: set[int] = set()
        self.discarded = 0  # copies in flight when their sender or receiver left
        self.fault_rng = fault_rng
        self._bursts: list[_LinkFault] = []
        self._delays: list[_LinkFault] = []
        self.fault_stats = {k: np.zeros(self.n_robots, dtype=np.int64) for k in FAULT_STATS}

    def _check_robot(self, robot: int) -> None:
        if isinstance(robot, bool) or not isinstance(robot, int | np.integer):
            raise ValueError(f"robot must be an integer in 0..{self.n_robots - 1}, got {robot!r}")
        if not 0 <= robot < self.n_robots:
            raise ValueError(f"robot must be in 0..{self.n_robots - 1}, got {robot}")

    def _check_window(self, robot: int, first_step: int, end_step: int) -> None:
        self._check_robot(robot)
        for name, step in (("first_step", first_step), ("end_step", end_step)):
            if isinstance(step, bool) or not isinstance(step, int | np.integer):
                raise ValueError(f"{name} must be an integer control step, got {step!r}")
        if not 0 <= first_step <= end_step:
            raise ValueError(f"need 0 <= first_step <= end_step, got {first_step}, {end_step}")

    def add_burst(self, robot: int, first_step: int, end_step: int, prob: float = 1.0) -> None:
        """Lose the copies sent by or to ``robot`` at steps [first_step, end_step), each with
        probability ``prob`` (drawn from ``fault_rng`` when below 1)."""
        self._check_window(robot, first_step, end_step)
        if not (_is_number(prob) and 0.0 < prob <= 1.0):
            raise ValueError(f"prob must be a probability in (0, 1], got {prob!r}")
        if prob < 1.0 and self.fault_rng is None:
            raise ValueError("a burst with prob < 1 needs the channel's fault_rng")
        self._bursts.append(_LinkFault(int(robot), int(first_step), int(end_step), float(prob)))

    def add_delay(self, robot: int, first_step: int, end_step: int, delay_s: float) -> None:
        """Delay the copies ``robot`` sends at steps [first_step, end_step) by ``delay_s``
        beyond the latency (rounded to whole periods)."""
        self._check_window(robot, first_step, end_step)
        if not (_is_number(delay_s) and np.isfinite(delay_s) and delay_s >= 0):
            raise ValueError(f"delay_s must be a finite number >= 0 s, got {delay_s!r}")
        extra = _periods(float(delay_s), self.dt_s)
        self._delays.append(_LinkFault(int(robot), int(first_step), int(end_step), 1.0, extra))

    def disconnect(self, robot: int) -> None:
        """``robot`` leaves the channel (it let go of the cargo): the copies in flight from or to
        it are discarded, and it neither sends nor receives any more."""
        self._check_robot(robot)
        robot = int(robot)
        self.disconnected.add(robot)
        for due in list(self._queue):
            kept = [
                (receiver, msg)
                for receiver, msg in self._queue[due]
                if receiver != robot and msg.sender != robot
            ]
            discarded = len(self._queue[due]) - len(kept)
            self.discarded += discarded
            self.stats["in_flight"] -= discarded
            if kept:
                self._queue[due] = kept
            else:
                del self._queue[due]

    def _lost_to_burst(self, sender: int, receiver: int, step: int) -> bool:
        for burst in self._bursts:
            if burst.robot in (sender, receiver) and burst.active(step):
                if burst.prob >= 1.0 or self.fault_rng.random() < burst.prob:
                    return True
        return False

    def send(self, message: Any, step: int | None = None) -> None:
        """Publish ``message`` (a dataclass with ``sender``, ``wrench_grasp``, ``wrench_world``
        and ``grasp_rot_world`` fields) at control step ``step`` (default: its ``stamp``)."""
        if not dataclasses.is_dataclass(message) or isinstance(message, type):
            raise ValueError(f"message must be a dataclass instance, got {type(message).__name__}")
        sender = getattr(message, "sender", None)
        if isinstance(sender, bool) or not isinstance(sender, int | np.integer):
            raise ValueError(f"message.sender must be an integer, got {sender!r}")
        if not 0 <= sender < self.n_robots:
            raise ValueError(f"message.sender must be in 0..{self.n_robots - 1}, got {sender}")
        if sender in self.disconnected:
            raise ValueError(f"robot {sender} has left the channel (disconnect): it cannot send")
        if step is None:
            step = getattr(message, "stamp", None)
        if isinstance(step, bool) or not isinstance(step, int | np.integer):
            raise ValueError(f"step must be an integer control step, got {step!r}")
        self.stats["sent"] += 1
        step = int(step)
        extra = sum(d.extra_steps for d in self._delays if d.robot == sender and d.active(step))
        due = step + self.latency_steps + extra
        shared = not self._noisy and _is_frozen(message)  # then every receiver gets it as is
        for receiver in range(self.n_robots):
            if receiver == sender or receiver in self.disconnected:
                continue
            if self.drop_prob > 0 and self.rng.random() < self.drop_prob:
                self.stats["dropped"] += 1
                continue
            copy = message if shared else self._copy(message)
            if self._bursts and self._lost_to_burst(sender, receiver, step):
                self.fault_stats["lost_sent"][sender] += 1
                self.fault_stats["lost_received"][receiver] += 1
                continue
            if extra:
                self.fault_stats["delayed_sent"][sender] += 1
                self.fault_stats["delayed_received"][receiver] += 1
            self._queue[due].append((receiver, copy))
            self.stats["in_flight"] += 1

    def _copy(self, message: Any) -> Any:
        """A copy of ``message`` with this copy's wrench noise added: its class called with its
        fields (``dataclasses.replace`` with the arrays changed, without looking the fields up
        again at every copy), each writable array copied (once where fields share it, the
        copies sharing it alike), the read-only ones shared."""
        fields = {name: getattr(message, name) for name in _init_fields(type(message))}
        noisy = self._noisy
        copies: dict[int, np.ndarray] = {}
        for name, value in fields.items():
            if not isinstance(value, np.ndarray) or not value.flags.writeable:
                continue
            if not (noisy and name in WRENCH_FIELDS):
                if id(value) not in copies:
                    copies[id(value)] = value.copy()
                fields[name] = copies[id(value)]
        if noisy:  # the noisy wrenches are new arrays
            noise_grasp = self._wrench_noise_std * self.rng.standard_normal(6)
            rot = np.asarray(message.grasp_rot_world, dtype=float)
            noise_world = np.concatenate((rot @ noise_grasp[:3], rot @ noise_grasp[3:]))
            for name, noise in zip(WRENCH_FIELDS, (noise_grasp, noise_world), strict=True):
                fields[name] = fields[name] + noise
        return type(message)(**fields)

    def due(self, step: int) -> bool:
        """Whether ``deliver(step)`` has any copy to hand out."""
        return bool(self._queue) and min(self._queue) <= step

    def deliver(self, step: int) -> dict[int, list[Any]]:
        """The copies due at control step ``step`` (and any older ones not yet collected), per
        receiver; every robot index is a key. Each copy is delivered once."""
        out: dict[int, list[Any]] = {r: [] for r in range(self.n_robots)}
        for due in sorted(d for d in self._queue if d <= step):
            copies = self._queue.pop(due)
            for receiver, message in copies:
                out[receiver].append(message)
            self.stats["delivered"] += len(copies)
            self.stats["in_flight"] -= len(copies)
        return out
