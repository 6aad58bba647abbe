"""The robots' communication channel: latency, message loss and additive wrench noise.

Every message a robot publishes goes to every other robot. Per message and per receiver the
channel decides, at send time, whether the copy is lost (probability ``drop_prob``) and draws the
additive Gaussian noise on its wrench; a kept copy arrives ``latency_steps`` control periods
after it was sent (``latency_s`` rounded to the nearest whole period, halves up: a control loop
reads its mailbox once per period). Each receiver gets its own copy (arrays copied), so one
receiver cannot alter what another one sees.

Noise: a wrench [force N; moment N m] drawn with standard deviations ``noise_std`` =
(force, moment) per axis in the sender's grasp frame is added to ``wrench_grasp``; the same
perturbation, rotated with the message's ``grasp_rot_world``, is added to ``wrench_world``, so the
two fields keep describing one wrench (isotropic noise has the same law in either frame).

All randomness comes from the ``np.random.Generator`` given to the constructor, drawn in a fixed
order (per message: receivers in increasing index, drop then noise), so a seeded channel is
reproducible.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from typing import Any

import numpy as np

WRENCH_FIELDS = ("wrench_grasp", "wrench_world")


class CommChannel:
    """Delivers the robots' messages with latency, loss and noise.

    Args:
        n_robots: robots on the channel; messages carry a ``sender`` index in ``0..n_robots-1``.
        latency_s: delay of every message in seconds, rounded to whole control periods (>= 0).
        drop_prob: probability in [0, 1] that one copy (one message to one receiver) is lost.
        noise_std: (force N, moment N m) standard deviation of the additive wrench noise per axis.
        dt_s: control period in seconds.
        rng: the generator every random draw comes from.
    """

    def __init__(
        self,
        n_robots: int,
        latency_s: float,
        drop_prob: float,
        noise_std: tuple[float, float],
        dt_s: float,
        rng: np.random.Generator,
    ) -> None:
        if isinstance(n_robots, bool) or not isinstance(n_robots, int | np.integer):
            raise ValueError(f"n_robots must be a positive integer, got {n_robots!r}")
        if n_robots < 1:
            raise ValueError(f"n_robots must be a positive integer, got {n_robots}")
        if not (isinstance(dt_s, int | float) and np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive finite number of seconds, got {dt_s!r}")
        if not (isinstance(latency_s, int | float) and np.isfinite(latency_s) and latency_s >= 0):
            raise ValueError(f"latency_s must be a finite number >= 0 s, got {latency_s!r}")
        if not (isinstance(drop_prob, int | float) and 0.0 <= drop_prob <= 1.0):
            raise ValueError(f"drop_prob must be a probability in [0, 1], got {drop_prob!r}")
        noise = np.asarray(noise_std, dtype=float)
        if noise.shape != (2,) or not np.all(np.isfinite(noise)) or np.any(noise < 0):
            raise ValueError(
                f"noise_std must be two finite numbers >= 0 (force N, moment N m), "
                f"got {noise_std!r}"
            )
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        self.n_robots = int(n_robots)
        self.dt_s = float(dt_s)
        self.latency_s = float(latency_s)
        # Nearest whole period, halves up (round() takes halves to even: 0.2 s at 16 ms would be
        # 12 periods); the tiny margin absorbs float error in latency / dt.
        self.latency_steps = int(np.floor(self.latency_s / self.dt_s + 0.5 + 1e-9))
        self.drop_prob = float(drop_prob)
        self.noise_std = noise
        self.rng = rng
        self._queue: dict[int, list[tuple[int, Any]]] = defaultdict(list)  # due step -> copies
        self.stats = {"sent": 0, "delivered": 0, "dropped": 0, "in_flight": 0}

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
        if step is None:
            step = getattr(message, "stamp", None)
        if isinstance(step, bool) or not isinstance(step, int | np.integer):
            raise ValueError(f"step must be an integer control step, got {step!r}")
        self.stats["sent"] += 1
        due = int(step) + self.latency_steps
        for receiver in range(self.n_robots):
            if receiver == sender:
                continue
            if self.drop_prob > 0 and self.rng.random() < self.drop_prob:
                self.stats["dropped"] += 1
                continue
            self._queue[due].append((receiver, self._copy(message)))
            self.stats["in_flight"] += 1

    def _copy(self, message: Any) -> Any:
        """An independent copy of ``message`` with this copy's wrench noise added."""
        changes = {
            f.name: np.array(getattr(message, f.name), copy=True)
            for f in dataclasses.fields(message)
            if isinstance(getattr(message, f.name), np.ndarray)
        }
        if np.any(self.noise_std > 0):
            std = np.repeat(self.noise_std, 3)
            noise_grasp = std * self.rng.standard_normal(6)
            rot = np.asarray(message.grasp_rot_world, dtype=float)
            noise_world = np.concatenate((rot @ noise_grasp[:3], rot @ noise_grasp[3:]))
            for name, noise in zip(WRENCH_FIELDS, (noise_grasp, noise_world), strict=True):
                changes[name] = changes[name] + noise
        return dataclasses.replace(message, **changes)

    def deliver(self, step: int) -> dict[int, list[Any]]:
        """The copies due at control step ``step`` (and any older ones not yet collected), per
        receiver; every robot index is a key. Each copy is delivered once."""
        out: dict[int, list[Any]] = {r: [] for r in range(self.n_robots)}
        for due in sorted(d for d in self._queue if d <= step):
            for receiver, message in self._queue.pop(due):
                out[receiver].append(message)
                self.stats["delivered"] += 1
                self.stats["in_flight"] -= 1
        return out
