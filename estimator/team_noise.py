"""The team's noise maps of one update instant (``noise_model.NoiseModel.motion_noise``): this
robot's and its peers' motion noise stacked (``stacked_motion``), mapped into the balance and the
peers' grasp-acceleration mismatches in one compiled call (``team_maps``, ``team_maps_of``); and
the excitation gate's signal-to-noise ratio (``excitation_snr_kernel``)."""

from __future__ import annotations

import itertools
import operator

import numpy as np
from numba import njit

from .geometry import matmul3_into, matvec3_into
from .motion import balance_noise_map_kernel, conditioned_noise, psd_factor

_NO_COV = np.zeros((10, 10))  # ``team_noise`` without the posterior's spread


@njit(cache=True)
def _product_into(out, a, b):
    """out = a b (m, n) of an (m, l) and an (l, n) matrix, any strides (views of the team's
    maps), sum_k a_ik b_kj as one loop: a BLAS call costs more than these few multiply-adds."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for k in range(a.shape[1]):
                total += a[i, k] * b[k, j]
            out[i, j] = total


@njit(cache=True)
def team_maps(params, d_links, d_y, regressor, transforms, peer_links, peer_grasp, peer_acc,
               peer_start):  # fmt: skip
    """The team's stacked maps of ``NoiseModel.motion_noise``: noise map N (6, n) over the
    motion of this robot (its n_own coordinates first) and its peers (peer k's from column
    n_own + peer_start[k]), mismatch map D (3 P, n) and mismatch d (3 P,).

    Peer k (T = ``transforms[k]`` G_k -> G, R its rotation, p the peer's grasp point in G, read
    from the moment rows' [p]x R): N's block T L_k; D's rows 3k..3k+2 are -G_i(p) over this
    robot's columns and R G_k over the peer's; d_k = R a_Gk - (a_G + (skew(wd) + skew(w)^2) p),
    a_G and the h block from the filtered ``regressor``. The products are loops
    (``_product_into``, ``geometry.matmul3_into``, ``geometry.matvec3_into``)."""
    n_own, n_peers = d_y.shape[0], transforms.shape[0]
    n_map = np.zeros((6, n_own + peer_links.shape[1]))
    d_map = np.zeros((3 * n_peers, n_map.shape[1]))
    mismatch = np.empty(3 * n_peers)
    n_map[:, :n_own] = balance_noise_map_kernel(d_links, d_y, params)
    ang_g = regressor[:3, 1:4]  # skew(wd) + skew(w)^2
    lever, pos = np.empty((3, 3)), np.empty(3)
    turned_acc, lever_acc = np.empty(3), np.empty(3)
    for k in range(n_peers):
        rot = transforms[k, :3, :3]
        matmul3_into(lever, transforms[k, 3:, :3], rot.T)
        pos[0], pos[1], pos[2] = lever[2, 1], lever[0, 2], lever[1, 0]
        cols = slice(n_own + peer_start[k], n_own + peer_start[k + 1])
        peer = slice(peer_start[k], peer_start[k + 1])
        _product_into(n_map[:, cols], transforms[k], peer_links[:, peer])
        for c in range(n_own):  # -G_i(p) = -(d a_G + d h p), as ``motion.grasp_acc_map_kernel``
            for i in range(3):
                lever_c = d_y[c, i, 1] * pos[0] + d_y[c, i, 2] * pos[1] + d_y[c, i, 3] * pos[2]
                d_map[3 * k + i, c] = -(d_y[c, i, 0] + lever_c)
        _product_into(d_map[3 * k : 3 * k + 3, cols], rot, peer_grasp[:, peer])
        matvec3_into(turned_acc, rot, peer_acc[k])
        matvec3_into(lever_acc, ang_g, pos)
        for i in range(3):
            mismatch[3 * k + i] = turned_acc[i] - (regressor[i, 0] + lever_acc[i])
    return n_map, d_map, mismatch


def same_key(a: tuple, b: tuple) -> bool:
    """Whether two ``NoiseModel._team`` keys (the parameters' bytes, the other inputs' objects)
    name the same instant: equal bytes, the same objects."""
    return a[0] == b[0] and len(a[1]) == len(b[1]) and all(map(operator.is_, a[1], b[1]))


def stacked_motion(own, params, d_links, d_y, regressor, peers):
    """This robot's and the peers' motion noise stacked for ``team_maps``: per-coordinate
    variances and band weights (n_own + sum n_j,), the peers' (T_ij, d links_j, d a_Gj,
    a_Gj) as arrays, and each peer's first coordinate; ValueError on inconsistent shapes."""
    var = np.concatenate([own.var] + [m.motion_var for _, m in peers])
    band = np.concatenate([own.band] + [m.motion_band for _, m in peers])
    sizes = [np.shape(m.motion_links_jac)[1] for _, m in peers]
    if var.shape != (np.shape(d_y)[0] + sum(sizes),) or band.shape != var.shape:
        raise ValueError(
            f"motion variances ({var.size}) and bands ({band.size}) must match the "
            f"Jacobians' {np.shape(d_y)[0]} + {sizes} coordinates"
        )
    if peers:
        # np.array and np.concatenate: the stacks without numpy's Python-level wrappers.
        transforms = np.array([t for t, _ in peers], dtype=float)
        peer_links = np.concatenate([m.motion_links_jac for _, m in peers], axis=1, dtype=float)
        peer_grasp = np.concatenate([m.motion_grasp_jac for _, m in peers], axis=1, dtype=float)
        peer_acc = np.array([m.grasp_acc for _, m in peers], dtype=float)
    else:
        transforms, peer_links = np.zeros((0, 6, 6)), np.zeros((6, 0))
        peer_grasp, peer_acc = np.zeros((3, 0)), np.zeros((0, 3))
    n_own, n_peers = np.shape(d_y)[0], len(peers)
    shapes = (np.shape(params), np.shape(d_links), np.shape(d_y), np.shape(regressor),
              transforms.shape, peer_links.shape, peer_grasp.shape, peer_acc.shape)  # fmt: skip
    expected = ((10,), (6, n_own), (n_own, 6, 10), (6, 10), (n_peers, 6, 6),
                (6, sum(sizes)), (3, sum(sizes)), (n_peers, 3))  # fmt: skip
    if shapes != expected:
        raise ValueError(
            f"params, motion_jac, regressor and the peers' (transform, motion_links_jac, "
            f"motion_grasp_jac, grasp_acc) have shapes {shapes}, expected {expected}"
        )
    offsets = np.array([0, *itertools.accumulate(sizes)], dtype=np.int64)
    return var, band, (transforms, peer_links, peer_grasp, peer_acc), offsets


def team_maps_of(own, params, motion_jac, regressor, peers):
    """The team's noise map N (6, n), mismatch map D (3 P, n), mismatch d (3 P,) (``team_maps``)
    and the per-mode levels var * band (n,), for ``own`` (``noise_model.MotionNoiseSpec``) and
    ``peers`` [(T_ij, message)] (``noise_model.NoiseModel.motion_noise``)."""
    args, level = _team_args(own, params, motion_jac, regressor, peers)
    return (*team_maps(*args), level)


def team_noise(own, params, motion_jac, regressor, peers, condition, mismatch_model_var,
               params_cov):  # fmt: skip
    """``NoiseModel.motion_noise``'s mean (6,) and covariance (6, 6) of one instant, and this
    robot's modes as the residual sees them (6, n_own), in one compiled call
    (``team_noise_kernel``): the team's maps (``team_maps``) conditioned on the mismatch or not
    (``motion.conditioned_noise``), with the spread of ``params_cov`` (None: none)."""
    args, level = _team_args(own, params, motion_jac, regressor, peers)
    spread = params_cov is not None
    cov = np.ascontiguousarray(params_cov, dtype=float) if spread else _NO_COV
    return team_noise_kernel(*args, level, condition, mismatch_model_var, cov, spread)


def _team_args(own, params, motion_jac, regressor, peers):
    """``team_maps``' arguments (``stacked_motion``, the arrays contiguous floats) and the
    per-mode levels var * band."""
    d_links, d_y = motion_jac
    var, band, stacked, offsets = stacked_motion(own, params, d_links, d_y, regressor, peers)
    arrays = (
        np.ascontiguousarray(params, dtype=float),
        np.ascontiguousarray(d_links, dtype=float),
        np.ascontiguousarray(d_y, dtype=float),
        np.ascontiguousarray(regressor, dtype=float),
    )
    return (*arrays, *stacked, offsets), var * band


@njit(cache=True)
def team_noise_kernel(params, d_links, d_y, regressor, transforms, peer_links, peer_grasp,
                      peer_acc, peer_start, level, condition, mismatch_model_var, params_cov,
                      with_spread):  # fmt: skip
    """``team_maps`` then ``motion.conditioned_noise`` on its maps (``team_noise``)."""
    n_map, d_map, mismatch = team_maps(params, d_links, d_y, regressor, transforms, peer_links,
                                       peer_grasp, peer_acc, peer_start)  # fmt: skip
    return conditioned_noise(n_map, d_map, mismatch, level, condition, mismatch_model_var, d_y,
                             params_cov, with_spread)  # fmt: skip


@njit(cache=True)
def excitation_snr_kernel(regressor, acc_noise, ang_noise, lever_m):
    """The larger of |a_G| / sigma_lin and |wd| / sigma_ang, sigma_lin = hypot(sigma_a,
    L sigma_ang) at the base-to-grasp lever L (m); a_G (m/s^2) and wd (rad/s^2) from the
    filtered regressor (6, 10), whose force rows' h-columns are skew(wd) + skew(w)^2 (wd is
    their antisymmetric part)."""
    acc = regressor[:3, 0]
    h = regressor[:3, 1:4]
    wd = 0.5 * np.array((h[2, 1] - h[1, 2], h[0, 2] - h[2, 0], h[1, 0] - h[0, 1]))
    lin_noise = np.hypot(acc_noise, lever_m * ang_noise)
    snr_lin = np.linalg.norm(acc) / max(lin_noise, 1e-300)
    snr_ang = np.linalg.norm(wd) / max(ang_noise, 1e-300)
    return max(snr_lin, snr_ang)


@njit(cache=True)
def message_map(d_links, d_y, mode_std):
    """The modes' map a peer sees, M diag(s) (9, n): M = [L; A], the links' map L = d links
    (6, n) over the grasp acceleration's A = d Y[:, :3, 0]^T (3, n), each mode k scaled by its
    std s_k (``NoiseModel.message_modes``)."""
    n = d_y.shape[0]
    out = np.empty((9, n))
    out[:6] = d_links * mode_std
    for k in range(n):
        out[6:, k] = d_y[k, :3, 0] * mode_std[k]
    return out


@njit(cache=True)
def message_factor(d_links, d_y, mode_std):
    """F (9, 9) with F F^T = M M^T, M the modes' map a peer sees (``message_map``), M M^T by
    numba's product and F by ``motion.psd_factor``: what ``NoiseModel.message_modes`` sends
    and ``instant_kernels.record_modes`` makes in its call, the same arithmetic in both."""
    stacked = message_map(d_links, d_y, mode_std)
    return psd_factor(stacked @ stacked.T)
