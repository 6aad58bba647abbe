"""The cargo model's feed-forward as an input of a learned residual (docs/learning.md).

A residual policy on the no-model scripted controller has to add what a cargo model adds to that
controller's thrust: about m_est (a_ref + K_d e_v + K_p e_p) for the force and I_est w'_ref +
w x I_est w for the torque, allocated to the robots through the grasp geometry. Its feed-forward
part, the cargo model times the reference's accelerations, is a product of an estimate and a
reference that changes sign along the trajectory; a small MLP builds such a product slowly from
PPO's gradients. ``FeedForwardObservation`` computes it for the policy, per robot, in that
robot's action units:

    u_ff,i(pi) = u_i(pi; a = a_ref, w' = w'_ref) - u_i(none; a = a_ref, w' = w'_ref)

where u_i(model; a, w') is robot i's share of the scripted controller's allocated thrust (its
six thrust entries, force and torque in its base frame, as fractions of its thrust limits: the
residual's own units) with the composite body of the robots plus the cargo model ``pi`` (or no
cargo), when the desired accelerations are the reference's alone (the PD gains zero). It is the
cargo's share of ``team_wrench`` M (a + w' x (c - p) + w x (w x (c - p))), I_c w' + w x I_c w
(and of the arms' motion wrench, whose centre of mass moves with the cargo) at the measured
angular rate and arm angles. ``pi`` is each robot's live estimate (``"estimate"``: the
``estimate_mean`` block of its observation, grasp frame) or the estimator's prior
(``"prior"``: ``default_prior``, the value the estimate starts from), so that a policy that does
not observe the estimates gets an input of the same form without the cargo's information. When
the tracking errors are zero (and the arms at rest) it equals the scripted controller's full
correction a_estimate - a_none (``ModelCorrection``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from astrocargo.estimator.prior import default_prior

from .controllers import CooperativeController, ObservationController

FEEDFORWARD_SOURCES = ("estimate", "prior")
FEEDFORWARD_DIM = 6  # per robot: force (3) and torque (3) thrust entries, fractions of limits


class FeedForwardController(ObservationController):
    """``ObservationController`` with zero PD gains (a = a_ref, w' = w'_ref: the feed-forward
    only). ``for_env(env, cargo_model)`` takes the controller's cargo models and "prior":
    ``default_prior`` of each robot, in its grasp frame (the fixed-parameter path of "truth"
    with ``prior_in_grasp`` (n, 10) in place of the truth)."""

    def __init__(self, *args: Any, prior_in_grasp: np.ndarray | None = None, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.team = CooperativeController(self.robots, 0.0, 0.0, 0.0, 0.0)
        if prior_in_grasp is not None:
            self._truth_in_grasp = np.asarray(prior_in_grasp, dtype=float)

    @classmethod
    def for_env(cls, env, cargo_model: str = "estimate", **kwargs: Any) -> FeedForwardController:
        if cargo_model != "prior":
            return super().for_env(env, cargo_model, **kwargs)
        sim = env.sim
        prior = np.stack([default_prior(robot) for robot in sim.robots])
        agents = list(env.possible_agents)
        layout, zeros = sim.obs_layout, np.zeros(10)
        return cls(
            sim.robots,
            sim.handrail_pose,
            layout,
            "truth",
            zeros,
            agents=agents,
            prior_in_grasp=prior,
            **kwargs,
        )


class FeedForwardObservation:
    """u_ff,i of every acting robot (module docstring) from the env's observations, with the
    cargo model ``source`` ("estimate" or "prior")."""

    def __init__(self, env: Any, source: str) -> None:
        if source not in FEEDFORWARD_SOURCES:
            raise ValueError(f"source must be one of {FEEDFORWARD_SOURCES}, got {source!r}")
        self.source = source
        self.with_cargo = FeedForwardController.for_env(env, source)
        self.without_cargo = FeedForwardController.for_env(env, "none")

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """agent -> u_ff (6,) for the agents of ``obs`` (the robots holding the cargo)."""
        with_cargo = self.with_cargo.predict(obs)[0]
        without = self.without_cargo.predict(obs)[0]
        return {a: with_cargo[a][:FEEDFORWARD_DIM] - without[a][:FEEDFORWARD_DIM] for a in obs}
