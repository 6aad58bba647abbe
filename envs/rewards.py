"""The reward terms (the env docstring's section Rewards): per robot, the team's and its own
(individual) value of each term, mixed as shared * team + (1 - shared) * individual and
weighted; the reward is their sum."""

from __future__ import annotations

import numpy as np
from numba import njit

from astrocargo.envs.config import REWARD_TERMS

ROTATION_WEIGHT_M_PER_RAD = 0.5  # tracking term: metres of position error per radian


@njit(cache=True)
def mix_rewards(track, effort, info, robot_contacts, cargo_contacts, acting, weights, shared):
    """Weighted, mixed terms (4, N) in ``REWARD_TERMS`` order and their sum per robot (N,).

    ``track`` (the team's tracking term, the same for every robot) is a scalar; ``effort`` and
    ``info`` (N,) are individual; the contact term is -(a robot's own contacts + the cargo's),
    its team value -(every contact). The team value of effort and info is their mean over the
    ``acting`` robots; the others' entries are 0."""
    n = effort.shape[0]
    individual = np.empty((4, n))
    individual[0, :] = track
    individual[1], individual[2] = effort, info
    individual[3] = -(robot_contacts + cargo_contacts).astype(np.float64)
    count = 0
    for i in range(n):
        count += acting[i]
    team = np.empty(4)
    for t in range(4):
        total = 0.0
        for i in range(n):
            if acting[i]:
                total += individual[t, i]
        team[t] = total / count
    team[0], team[3] = track, -float(robot_contacts.sum() + cargo_contacts)
    mixed, rewards = np.zeros((4, n)), np.zeros(n)
    for i in range(n):
        if not acting[i]:
            continue
        for t in range(4):
            mixed[t, i] = weights[t] * (shared * team[t] + (1.0 - shared) * individual[t, i])
            rewards[i] += mixed[t, i]
    return mixed, rewards


def reward_terms(
    track: float,
    effort: np.ndarray,
    info: np.ndarray,
    robot_contacts: np.ndarray,
    cargo_contacts: int,
    acting: np.ndarray,
    weights: np.ndarray,
    shared: float,
) -> tuple[dict[str, list[float]], np.ndarray]:
    """Every term per robot by name, weighted and mixed, and the reward per robot; the contact
    term counts a robot's own contacts plus the cargo's (team: every contact)."""
    mixed, rewards = mix_rewards(
        float(track), effort, info, robot_contacts, int(cargo_contacts), acting, weights,
        float(shared),
    )  # fmt: skip
    return dict(zip(REWARD_TERMS, mixed.tolist(), strict=True)), rewards
