"""What the cargo estimators exchange and keep: the message a robot publishes per update instant
(``WrenchMessage``), its own record of an instant (``Instant``) and the running average of a
peer's grasp pose relative to its own (``RelativeGrasp``).

Frames: G is the robot's grasp frame (fixed to the cargo), moments about its origin; world axes
where a name says so. Units: N, N m, m, m/s^2.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .copies import deepcopy_state
from .rne import wrench_transform


def _project_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to a 3x3 matrix: U diag(1, 1, det(U V^T)) V^T."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


@dataclass(frozen=True)
class WrenchMessage:
    """What robot ``sender`` publishes at control step ``stamp``."""

    sender: int
    stamp: int
    wrench_grasp: np.ndarray  # (6,) on the cargo: [f N; moment about the grasp point N m], G axes
    wrench_world: np.ndarray  # (6,) the same in world axes (with the sender's attitude estimate)
    grasp_pos_world: np.ndarray  # (3,) m
    grasp_rot_world: np.ndarray  # (3, 3)
    fix: bool  # grasp pose from a localization fix at this stamp
    wrench_cov_grasp: np.ndarray  # (6, 6) per-step covariance of the sender's actuation noise
    tainted: bool = False  # built from held readings (a missing or bad sample): do not use
    # The sender's filtered motion and its noise (``motion``), when it runs motion_fusion:
    grasp_acc: np.ndarray | None = None  # (3,) filtered acceleration of the grasp point, G axes
    motion_links_jac: np.ndarray | None = None  # (6, n) d links_G / d xi (xi: a_B, wd_B, qdd)
    motion_grasp_jac: np.ndarray | None = None  # (3, n) d grasp_acc / d xi
    motion_var: np.ndarray | None = None  # (n,) per-sample variance of the filtered xi's noise
    motion_band: np.ndarray | None = None  # (n,) its weight per update (motion.band_factors)


@dataclass
class Instant:
    """One of the robot's own update instants, waiting for its peers' messages."""

    thrust: np.ndarray  # all in the grasp frame, moments about the grasp point
    links: np.ndarray
    regressor: np.ndarray
    act_cov: np.ndarray  # per-step covariance of the own actuation noise, grasp frame
    tainted: bool
    motion_jac: tuple[np.ndarray, np.ndarray] | None = None  # (d links (6, n), d Y (n, 6, 10))


@dataclass
class RelativeGrasp:
    """A peer's grasp frame in this robot's: known (``known``, wrench transform) or the running
    sums of the fixes' relative poses."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    rot_sum: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    pos_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    count: int = 0
    known: np.ndarray | None = None  # the wrench transform, when the grasp layout is given
    # The averaged transform and the fix count it was made from (``transform``).
    _averaged: tuple[int, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def transform(self) -> np.ndarray:
        """The wrench transform (6, 6) from the peer's grasp frame to this robot's: the known
        one, or that of the fixes' average (the nearest rotation to the rotations' mean, the
        mean offset), made again only when a fix has been added. Read-only."""
        if self.known is not None:
            return self.known
        if self._averaged is None or self._averaged[0] != self.count:
            rot = _project_rotation(self.rot_sum)
            averaged = wrench_transform(rot, self.pos_sum / self.count)
            averaged.setflags(write=False)
            self._averaged = (self.count, averaged)
        return self._averaged[1]
