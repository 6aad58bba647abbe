"""The infos of a control step (the env docstring's section Infos): one new dict per robot at
every step, whose mutable values (lists, arrays, the ``comm`` and ``faults`` dicts) are new
too, so a dict or value the caller keeps never changes afterwards."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from astrocargo.envs.config import REWARD_TERMS

if TYPE_CHECKING:
    from astrocargo.envs.transport import CargoTransport

REWARD_KEYS = tuple(f"reward_{t}" for t in REWARD_TERMS)  # their names in infos


def step_infos(
    sim: CargoTransport,
    terms: np.ndarray,
    n_clipped: np.ndarray,
    wall_contacts: np.ndarray,
    reason: str | None,
    robots: tuple[int, ...],
    released: tuple[int, ...],
    saturated: np.ndarray | None = None,
) -> list[dict[str, Any] | None]:
    """Infos of ``robots`` (None for the others); ``terms`` (4, N): the weighted, mixed
    reward terms in ``REWARD_TERMS`` order, each per robot; ``released``: those letting go now;
    ``saturated`` (n_robots,): ``thrust_saturation`` of this step (zeros at reset)."""
    n = sim.n_robots
    infos: list[dict[str, Any] | None] = [None] * n
    comm = dict(sim.channel.stats)
    track, effort, gain, contact = terms.tolist()
    k_track, k_effort, k_info, k_contact = REWARD_KEYS
    n_clipped, wall_contacts = n_clipped.tolist(), wall_contacts.tolist()
    saturated = [0.0] * n if saturated is None else saturated.tolist()
    faults = sim.fault_schedule.infos(sim.step_count, sim.channel.fault_stats)
    time_s, releases, holding = float(sim.data.time), len(sim.released_at_s), sim.holding
    estimators = sim.estimators
    # One copy per step of each (n_robots, 10) array; each info gets its row of it.
    true_params = sim.true_params_grasp.copy()
    if estimators:
        est_mean, est_std = sim.est_mean.copy(), sim.est_std.copy()
    for i in robots:
        info: dict[str, Any] = {
            k_track: track[i],
            k_effort: effort[i],
            k_info: gain[i],
            k_contact: contact[i],
            "termination_reason": reason or ("released" if i in released else None),
            "releases": releases,
            "holding": list(holding),
            "time_s": time_s,
            "clipped_actions": n_clipped[i],
            "saturated": saturated[i],
            "wall_contacts": wall_contacts[i],
            "true_params": true_params[i],
            "comm": comm,
            "faults": faults[i],
        }
        if i in released:
            info["released_momentum"] = sim.released_momentum[i].copy()
        if estimators:
            info["estimate"] = est_mean[i]
            info["estimate_std"] = est_std[i]
            info["estimator"] = estimators[i].counters
            info |= sim.est_errors[i]
            info["principal_rel_err"] = list(info["principal_rel_err"])  # kept until a refresh
        infos[i] = info
    return infos
