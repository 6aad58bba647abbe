"""The process side of one update instant in one compiled call (``CargoEstimator._measurement``
for a team whose grasp layout is known, without peer noise, window or squared-rate terms): the
peers' wrenches and actuation covariance (``peer_sums``), the team's motion noise
(``team_noise.team_noise_kernel``) and the measurement's offset b and covariance R
(``instant_terms_kernel``), the peers' message arrays gathered without copies for one peer;
and the general path's peer terms (``peer_terms``)."""

from __future__ import annotations

import itertools
import operator

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


def _stacked(arrays: list, axis: int | None) -> np.ndarray:
    """``arrays`` concatenated along ``axis`` (None: stacked on a new first axis); one array is
    passed through (a view) without a copy."""
    if len(arrays) == 1:
        return arrays[0] if axis is not None else arrays[0][None]
    return np.concatenate(arrays, axis=axis) if axis is not None else np.array(arrays)


def known_transforms(rels: list) -> np.ndarray | None:
    """The peers' given wrench transforms G_k -> G (``RelativeGrasp.known``) stacked in peer
    order (P, 6, 6); None where a peer's grasp layout is not given."""
    if any(r.known is None for r in rels):
        return None
    return np.array([r.known for r in rels]) if rels else _NO_TRANSFORMS


def instant_terms(noise, condition, params, inst, transforms, msgs, params_cov, floor_cov,
                  update_every):  # fmt: skip
    """(b, R, own modes, E[n], Cov[n]) of ``instant_terms_kernel`` for an ``Instant``
    ``inst``, the peers' transforms (P, 6, 6) and messages ``msgs`` (P each), at ``params``
    (10,) with its spread ``params_cov`` (10, 10) and ``noise``'s ``momentum_motion``; None
    where the messages' motion arrays do not match their Jacobians (the general path raises)."""
    own, (d_links, d_y) = noise.momentum_motion, inst.motion_jac
    if msgs:
        var, band, peer_links, peer_grasp, acc, wrenches, covs, starts = _peer_stacks(msgs)
    else:
        var = band = _EMPTY[0][0]
        peer_links, peer_grasp, acc, wrenches = _EMPTY
        covs, starts = _NO_TRANSFORMS, _NO_STARTS
    n_own, n_peer = d_y.shape[0], peer_links.shape[1]
    n_var = (own.var.size, own.band.size, var.size, band.size, peer_grasp.shape[1])
    if n_var != (n_own, n_own, n_peer, n_peer, n_peer):
        return None
    spread = params_cov is not None
    cov = params_cov if spread else _NO_COV
    return instant_terms_kernel(
        params, d_links, d_y, inst.regressor, transforms, peer_links, peer_grasp, acc, starts,
        (own.var, var), (own.band, band), condition, noise.mismatch_model_var, cov, spread,
        inst.act_cov, wrenches, covs, floor_cov, float(update_every), inst.links,
    )  # fmt: skip


def _peer_stacks(msgs: list) -> tuple:
    """The peers' message arrays as ``instant_terms_kernel`` takes them, from one pass over
    ``msgs``: variances, bands, links and grasp Jacobians side by side (``_stacked``), the grasp
    accelerations, wrenches and covariances stacked, and each peer's first coordinate."""
    fields = [[] for _ in range(7)]
    var, band, links, grasp, acc, wrench, cov = fields
    for m in msgs:
        var.append(m.motion_var)
        band.append(m.motion_band)
        links.append(m.motion_links_jac)
        grasp.append(m.motion_grasp_jac)
        acc.append(m.grasp_acc)
        wrench.append(m.wrench_grasp)
        cov.append(m.wrench_cov_grasp)
    sizes = tuple([jac.shape[1] for jac in links])
    starts = _STARTS.get(sizes)
    if starts is None:
        starts = _STARTS.setdefault(sizes, np.array([0, *itertools.accumulate(sizes)]))
    same = all(map(operator.is_, band, var))  # one array each: stacked once
    var = _stacked(var, 0)
    return (
        var, var if same else _stacked(band, 0), _stacked(links, 1), _stacked(grasp, 1),
        _stacked(acc, None), _stacked(wrench, None), _stacked(cov, None), starts,
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


_EMPTY = (np.zeros((6, 0)), np.zeros((3, 0)), np.zeros((0, 3)), np.zeros((0, 6)))
_NO_TRANSFORMS = np.zeros((0, 6, 6))
_NO_STARTS = np.zeros(1, dtype=np.int64)
_STARTS: dict[tuple, np.ndarray] = {}  # each peers' sizes' first coordinates, made once
