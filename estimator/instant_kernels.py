"""The record side of an update instant in one compiled call (``record_modes``).

At each update instant a robot records its balance's sensor-noise modes in the momentum chain
and the 9 modes its message carries (``NoiseModel.momentum_jacobians``,
``NoiseModel.message_modes``). The pieces (the delayed pre-filter state, the regressor's
autocorrelation sums, the modes and the message's map M) are compiled here into one call over
the persistent state kept in preallocated arrays:
- the ring of recorded pre-filter states (``keep_motion``, ``nearest_motion``): stamps (K,),
  states (K, 3, 12 + nj), span [first slot, count] (2,);
- the autocorrelation's sums and ring (``motion.RegressorAutocorrelation``), in place.
The arithmetic is the same as the pieces' one by one, bit for bit. M M^T stays numpy's (a syrk:
a loop or numba's gemm rounds differently, and the message's factor, an eigendecomposition of
it, carries that into the team's conditioning: 2e-9 in open loop, past the same-results rule).
"""

from __future__ import annotations

from numba import njit

from .chain_modes import instant_noise_modes
from .motion import _add_regressor
from .team_noise import message_map


@njit(cache=True)
def keep_motion(stamps, states, span, stamp, pre_state, horizon):
    """Into the ring (``stamps`` (K,), ``states`` (K, 3, w), ``span`` [first, count], increasing
    stamps): drop the oldest states while their stamp is below ``horizon`` (steps), then append
    ``pre_state``[:3] recorded at ``stamp``. The caller leaves room for one (count < K):
    ValueError if there is none."""
    size = stamps.shape[0]
    first, count = span[0], span[1]
    while count > 0 and stamps[first] < horizon:
        first = (first + 1) % size
        count -= 1
    if count == size:
        raise ValueError("the ring of states is full")
    slot = (first + count) % size
    stamps[slot] = stamp
    states[slot] = pre_state[:3]
    span[0], span[1] = first, count + 1


@njit(cache=True)
def nearest_motion(stamps, states, span, target, dt_s):
    """The ring's state (value, derivative, second derivative) (3, w) recorded nearest ``target``
    (steps; of two as near, the earlier), moved the rest of the way along its derivatives (first
    order, ``dt_s`` s per step): x[:2] - (s - target) dt x[1:3]."""
    size = stamps.shape[0]
    first, count = span[0], span[1]
    i = 0  # the first recorded at or after the target (bisect_left)
    while i < count and stamps[(first + i) % size] < target:
        i += 1
    if i == count or (
        i > 0 and target - stamps[(first + i - 1) % size] <= stamps[(first + i) % size] - target
    ):
        i -= 1
    slot = (first + i) % size
    x = states[slot]
    back = (stamps[slot] - target) * dt_s
    moved = x.copy()
    moved[:2] -= back * x[1:3]
    return moved


@njit(cache=True)
def record_modes(arrays, imu_pos, n_joints, step_s, factors, point_factor, rate_terms, rate_var,
                 n_rate, mode_std, motion_ring, autocorrelation, stamp, pre_state, target,
                 horizon, dt_s, index, regressor, add):  # fmt: skip
    """An update instant's modes and its message's, in one call:
    1. the pre-filter's ``pre_state`` kept in ``motion_ring`` (stamps, states, span), drops
       below ``horizon`` (``keep_motion``), and x the state near ``target``
       (``nearest_motion``);
    2. with ``add``, the ``regressor`` (6, 10) of update ``index`` into the autocorrelation's
       sums (cross, power, ring, ring_power, ring_index) (``motion._add_regressor``);
    3. the modes d links - d thrust (6, n), d Y (n, 6, 10) at x
       (``chain_modes.instant_noise_modes``, with the channels' ``factors`` (6, 4, 4) and
       ``point_factor`` (8, 8));
    4. the message's map M = ``team_noise.message_map`` (9, n) of the modes scaled by
       ``mode_std`` (its factor F F^T = M M^T: ``NoiseModel.instant_modes``).
    Returns (d links, d Y, M)."""
    stamps, states, span = motion_ring
    keep_motion(stamps, states, span, stamp, pre_state, horizon)
    x = nearest_motion(stamps, states, span, target, dt_s)
    if add:
        cross, power, ring, ring_power, ring_index = autocorrelation
        _add_regressor(cross, power, ring, ring_power, ring_index, index, regressor)
    links, y = instant_noise_modes(arrays, imu_pos, x, n_joints, step_s, factors, point_factor,
                                   rate_terms, rate_var, n_rate)  # fmt: skip
    return links, y, message_map(links, y, mode_std)
