"""The process side of one update instant in one compiled call (``CargoEstimator._measurement``
for a team whose grasp layout is known, without peer noise, window or squared-rate terms): the
peers' wrenches and actuation covariance (``peer_sums``), the team's motion noise
(``team_noise.team_noise_kernel``) and the measurement's offset b and covariance R
(``instant_terms_kernel``), with the peers' message arrays unpacked from their flat buffers in
the same call (``packed_instant_terms``); and the general path's peer terms (``peer_terms``)."""

from __future__ import annotations

import itertools

import numpy as np
from numba import njit

from .team_noise import team_noise_kernel

_NO_COV = np.zeros((10, 10))  # the kernel without the posterior's spread


@njit(cache=True)
def peer_sums(act_cov, transforms, wrenches, covs):
    """The peers' side of an instant's balance (T_k = ``transforms[k]`` (6, 6), peer k's wrench
    transform G_k -> G): their wrenches on the cargo sum_k T_k w_k (6,) (``wrenches`` (P, 6))
    and the actuation covariance act_cov + sum_k T_k C_k T_k^T (6, 6) (``covs`` (P, 6, 6)),
    summed in peer order from zero and ``act_cov``."""
    wrench, cov = np.zeros(6), act_cov.copy()
    moved, half, carried = np.empty(6), np.empty((6, 6)), np.empty((6, 6))  # the products
    for k in range(transforms.shape[0]):
        t = transforms[k]
        np.dot(t, wrenches[k], moved)
        np.dot(t, covs[k], half)
        np.dot(half, t.T, carried)
        wrench += moved
        cov += carried
    return wrench, cov


@njit(cache=True)
def instant_terms_kernel(params, d_links, d_y, regressor, transforms, peer_links, peer_grasp,
                         peer_acc, peer_start, variances, bands, condition, mismatch_model_var,
                         params_cov, with_spread, act_cov, wrenches, covs, floor_cov,
                         update_every, links):  # fmt: skip
    """An update's offset b = links - sum_k T_k w_k - E[n] (6,), covariance
    R = floor + (act_cov + sum_k T_k C_k T_k^T) / update_every + Cov[n] (6, 6), this robot's
    modes as the residual sees them (6, n_own), and E[n] (6,), Cov[n] (6, 6): ``peer_sums``
    and ``team_noise_kernel`` (n the motion noise, its arguments as there; its levels
    var * band from this robot's ``variances[0]``, ``bands[0]`` (n_own,) and the peers'
    stacked ``variances[1]``, ``bands[1]``)."""
    n_own = variances[0].shape[0]
    level = np.empty(n_own + variances[1].shape[0])
    level[:n_own] = variances[0] * bands[0]
    level[n_own:] = variances[1] * bands[1]
    wrench, cov = peer_sums(act_cov, transforms, wrenches, covs)
    mean, motion_cov, modes = team_noise_kernel(
        params, d_links, d_y, regressor, transforms, peer_links, peer_grasp, peer_acc,
        peer_start, level, condition, mismatch_model_var, params_cov, with_spread,
    )  # fmt: skip
    return (
        links - wrench - mean,
        floor_cov + cov / update_every + motion_cov,
        modes,
        mean,
        motion_cov,
    )


def known_transforms(rels: list) -> np.ndarray | None:
    """The peers' given wrench transforms G_k -> G (``RelativeGrasp.known``) stacked in peer
    order (P, 6, 6); None where a peer's grasp layout is not given."""
    if any(r.known is None for r in rels):
        return None
    return np.array([r.known for r in rels]) if rels else _NO_TRANSFORMS


@njit(cache=True)
def unpack_peers(packed, starts):
    """The peers' packed buffers (``messages.PACKED_PARTS``) concatenated in peer order, peer k's
    (n_k = starts[k + 1] - starts[k] coordinates) from 11 starts[k] + 45 k, as
    ``instant_terms_kernel`` takes them: variances, bands (N,), links (6, N) and grasp (3, N)
    Jacobians side by side (N = starts[-1]), accelerations (P, 3), wrenches (P, 6) and
    covariances (P, 6, 6). Copies only."""
    n_peers, total = starts.shape[0] - 1, starts[-1]
    var, band = np.empty(total), np.empty(total)
    links, grasp = np.empty((6, total)), np.empty((3, total))
    acc, wrench, cov = np.empty((n_peers, 3)), np.empty((n_peers, 6)), np.empty((n_peers, 6, 6))
    for k in range(n_peers):
        lo, n = starts[k], starts[k + 1] - starts[k]
        o = 11 * lo + 45 * k
        for j in range(n):
            var[lo + j] = packed[o + j]
            band[lo + j] = packed[o + n + j]
            for i in range(6):
                links[i, lo + j] = packed[o + (2 + i) * n + j]
            for i in range(3):
                grasp[i, lo + j] = packed[o + (8 + i) * n + j]
        o += 11 * n
        for i in range(3):
            acc[k, i] = packed[o + i]
        for i in range(6):
            wrench[k, i] = packed[o + 3 + i]
            for j in range(6):
                cov[k, i, j] = packed[o + 9 + 6 * i + j]
    return var, band, links, grasp, acc, wrench, cov


@njit(cache=True)
def packed_instant_terms(params, d_links, d_y, regressor, transforms, packed, starts, own_var,
                         own_band, condition, mismatch_model_var, params_cov, with_spread,
                         act_cov, floor_cov, update_every, links):  # fmt: skip
    """``instant_terms_kernel`` on the peers' packed buffers (``unpack_peers``)."""
    var, band, peer_links, peer_grasp, acc, wrenches, covs = unpack_peers(packed, starts)
    return instant_terms_kernel(
        params, d_links, d_y, regressor, transforms, peer_links, peer_grasp, acc, starts,
        (own_var, var), (own_band, band), condition, mismatch_model_var, params_cov,
        with_spread, act_cov, wrenches, covs, floor_cov, update_every, links,
    )  # fmt: skip


def _starts(sizes: tuple) -> np.ndarray:
    """Each peer's first coordinate, then their total: [0, n_0, n_0 + n_1, ...] (made once)."""
    starts = _STARTS.get(sizes)
    if starts is None:
        starts = _STARTS.setdefault(sizes, np.array([0, *itertools.accumulate(sizes)]))
    return starts


def _one_peer(m) -> tuple | None:
    """One peer's message arrays as ``instant_terms_kernel`` takes them, as they are (views):
    variances, bands, links and grasp Jacobians, acceleration (1, 3), wrench (1, 6), covariance
    (1, 6, 6) and ``_starts``; None where its motion arrays do not match its Jacobians."""
    n = m.motion_links_jac.shape[1]
    if (m.motion_var.size, m.motion_band.size, m.motion_grasp_jac.shape[1]) != (n, n, n):
        return None
    return (
        m.motion_var, m.motion_band, m.motion_links_jac, m.motion_grasp_jac, m.grasp_acc[None],
        m.wrench_grasp[None], m.wrench_cov_grasp[None], _starts((n,)),
    )  # fmt: skip


def instant_terms(noise, condition, params, inst, transforms, msgs, params_cov, floor_cov,
                  update_every):  # fmt: skip
    """(b, R, own modes, E[n], Cov[n]) of ``instant_terms_kernel`` for an ``Instant``
    ``inst``, the peers' transforms (P, 6, 6) and messages ``msgs`` (P each), at ``params``
    (10,) with its spread ``params_cov`` (10, 10) and ``noise``'s ``momentum_motion``: one peer's
    arrays passed as they are (``_one_peer``), several peers' packed buffers concatenated
    (``packed_instant_terms``). None where a message's motion arrays do not match its
    Jacobians (it has no packed buffer) or the own ones do not (the general path raises)."""
    own, (d_links, d_y) = noise.momentum_motion, inst.motion_jac
    if (own.var.size, own.band.size) != (d_y.shape[0], d_y.shape[0]):
        return None
    spread = params_cov is not None
    cov = params_cov if spread else _NO_COV
    if len(msgs) == 1:
        peer = _one_peer(msgs[0])
        if peer is None:
            return None
        var, band, links, grasp, acc, wrenches, covs, starts = peer
        return instant_terms_kernel(
            params, d_links, d_y, inst.regressor, transforms, links, grasp, acc, starts,
            (own.var, var), (own.band, band), condition, noise.mismatch_model_var, cov, spread,
            inst.act_cov, wrenches, covs, floor_cov, float(update_every), inst.links,
        )  # fmt: skip
    buffers = [m.packed() for m in msgs]
    if any(b is None for b in buffers):
        return None
    starts = _starts(tuple([m.motion_links_jac.shape[1] for m in msgs]))
    return packed_instant_terms(
        params, d_links, d_y, inst.regressor, transforms,
        np.concatenate(buffers) if buffers else _NO_PACKED, starts, own.var, own.band,
        condition, noise.mismatch_model_var, cov, spread, inst.act_cov, floor_cov,
        float(update_every), inst.links,
    )  # fmt: skip


def peer_terms(act_cov, rels, msgs, peer_noise_cov, noise):
    """The peers' side of an instant's balance, all peers at once (T_j: peer j's wrench
    transform G_j -> G, ``rels[j].transform()``): their wrenches on the cargo sum_j T_j w_j
    (6,), the actuation covariance act_cov + sum_j T_j C_j T_j^T (6, 6) (C_j the message's),
    and the noise the peers add (6, 6): sum_j T_j N T_j^T (N ``peer_noise_cov``, None: none)
    and, for a grasp layout not given, the averaged relative pose's
    (``NoiseModel.relative_pose_cov`` of ``noise``). Sums run in peer order, from zero (the
    wrenches, the noise) or act_cov; the first two are ``peer_sums``, as on the compiled path."""
    added = np.zeros((6, 6))
    if not msgs:
        return np.zeros(6), act_cov.copy(), added
    transforms = np.array([rel.transform() for rel in rels])
    wrench, cov = peer_sums(
        act_cov, transforms, np.array([m.wrench_grasp for m in msgs]),
        np.array([m.wrench_cov_grasp for m in msgs]),
    )  # fmt: skip
    for k, rel in enumerate(rels):
        t = transforms[k]
        if peer_noise_cov is not None:
            added = added + t @ peer_noise_cov @ t.T
        if rel.known is None:
            added = added + noise.relative_pose_cov(t @ msgs[k].wrench_grasp, rel.count)
    return wrench, cov, added


_NO_TRANSFORMS = np.zeros((0, 6, 6))
_NO_PACKED = np.zeros(0)
_STARTS: dict[tuple, np.ndarray] = {}  # each peers' sizes' first coordinates, made once
