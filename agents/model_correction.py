"""How much the live cargo estimate changes the scripted controller's thrust along a flight:
the residual a policy on top of the no-model controller has to learn (docs/learning.md)."""

from __future__ import annotations

import numpy as np

from .controllers import ObservationController

CORRECTION_AFTER_S = 6.0  # the mass estimate is within 5 % by then (docs/learning.md)


class ModelCorrection:
    """What the live estimate changes in the scripted controller's thrust, along an episode: at
    every step from ``after_s`` on, per robot, the largest |a_estimate - a_none| over the six
    thrust entries of the actions of ``ObservationController`` with the "estimate" and the
    "none" cargo model from the same observation (fractions of each axis' thrust limit). It is
    the residual a policy on the no-model controller has to add to match the live-estimate
    controller; in the policy's action units it is this over ``residual_scale``."""

    def __init__(self, env, after_s: float = CORRECTION_AFTER_S) -> None:
        self.estimate = ObservationController.for_env(env, "estimate")
        self.none = ObservationController.for_env(env, "none")
        self.after_s = after_s
        self.values: list[np.ndarray] = []

    def record(self, obs: np.ndarray, time_s: float) -> None:
        if time_s >= self.after_s:
            diff = self.estimate.predict(obs)[0][:, :6] - self.none.predict(obs)[0][:, :6]
            self.values.append(np.abs(diff).max(axis=1))

    def metrics(self) -> dict[str, float]:
        """``correction_mean`` and ``correction_p95`` (95th percentile) over steps and robots."""
        values = np.concatenate(self.values) if self.values else np.full(1, np.nan)
        return {
            "correction_mean": float(np.mean(values)),
            "correction_p95": float(np.percentile(values, 95)),
        }
