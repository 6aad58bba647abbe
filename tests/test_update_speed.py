"""The compiled per-update kernels (rne._balance_jacobians, motion's conditioning and
noise modes, team_noise.team_maps, motion.posterior_spread and motion.gain_of) against the
plain forms they replace, and the update path's caches (the relative grasp, process's early
return)."""

from types import SimpleNamespace

import numpy as np
import pytest

from astrocargo.estimator.geometry import exp_so3
from astrocargo.estimator.motion import (
    condition_on_mismatch,
    grasp_acc_map,
    motion_jacobians,
    pinv_symmetric,
)
from astrocargo.estimator.noise_model import NoiseModel
from astrocargo.estimator.rne import (
    balance_motion_jacobians,
    links_and_regressor,
    wrench_transform,
)


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def _motion(rng, nj):
    return (rng.normal(size=3) * 0.4, rng.normal(size=3) * 0.2, rng.normal(size=3) * 0.1,
            rng.normal(size=nj), rng.normal(size=nj) * 0.3, rng.normal(size=nj) * 0.2)  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobians_equal_unit_differences_and_ignore_the_rates(seed):
    """The acceleration-part Jacobians equal the unit differences of the full balance (the
    former method) at any rates, and do not change when only the rates do."""
    robot = _robot()
    rng = np.random.default_rng(seed)
    w, wd, acc, q, qd, qdd = _motion(rng, robot.n_joints)

    def balance(xi):
        return links_and_regressor(robot, w, xi[3:6], xi[0:3], q, qd, xi[6:])

    d_links, d_y = balance_motion_jacobians(robot, w, wd, acc, q, qd, qdd)
    ref_links, ref_y = motion_jacobians(balance, np.concatenate((acc, wd, qdd)))
    scale_links, scale_y = np.abs(ref_links).max(), np.abs(ref_y).max()
    np.testing.assert_allclose(d_links, ref_links, rtol=0, atol=1e-12 * scale_links)
    np.testing.assert_allclose(d_y, ref_y, rtol=0, atol=1e-12 * scale_y)
    still = balance_motion_jacobians(robot, 0 * w, 0 * wd, 0 * acc, q, 0 * qd, 0 * qdd)
    np.testing.assert_array_equal(still[0], d_links)
    np.testing.assert_array_equal(still[1], d_y)
    with pytest.raises(ValueError, match="qd"):
        balance_motion_jacobians(robot, w, wd, acc, q, qd[:1], qdd)


def test_pinv_symmetric_is_numpy_s_hermitian_pinv():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(6, 4))
    for mat in (a @ a.T, a.T @ a, np.zeros((3, 3)), np.diag([1.0, -2.0, 1e-20])):
        expected = np.linalg.pinv(mat, hermitian=True)
        np.testing.assert_allclose(pinv_symmetric(mat), expected, rtol=0,
                                   atol=1e-12 * max(np.abs(expected).max(), 1e-300))  # fmt: skip


def _reference_motion_noise(model, params, jac, regressor, peers, fusion):
    """motion_noise's assembly written with lists and the public conditioning (the former
    code path)."""
    d_links, d_y = jac
    noise_maps = [d_links + np.einsum("kij,j->ik", d_y, params)]
    variances, bands = [model.motion.var], [model.motion.band]
    own_rows, peer_blocks, mismatch = [], [], []
    for t, m in peers:
        rot = t[:3, :3]
        lever = t[3:, :3] @ rot.T
        pos = np.array([lever[2, 1], lever[0, 2], lever[1, 0]])
        noise_maps.append(t @ m.motion_links_jac)
        variances.append(m.motion_var)
        bands.append(m.motion_band)
        own_rows.append(-grasp_acc_map(d_y, pos))
        peer_blocks.append(rot @ m.motion_grasp_jac)
        mismatch.append(rot @ m.grasp_acc - (regressor[:3, 0] + regressor[:3, 1:4] @ pos))
    if fusion == "own" or not peers:
        return condition_on_mismatch(noise_maps, [], variances, None, bands)
    maps = [np.vstack(own_rows)]
    for k, block in enumerate(peer_blocks):
        column = [np.zeros_like(block)] * len(peer_blocks)
        column[k] = block
        maps.append(np.vstack(column))
    return condition_on_mismatch(
        noise_maps, maps, variances, np.concatenate(mismatch), bands, model.mismatch_model_var
    )


@pytest.mark.parametrize("n_peers", [0, 1, 3])
@pytest.mark.parametrize("fusion", ["own", "team"])
def test_motion_noise_equals_the_list_assembly(n_peers, fusion):
    robot = _robot()
    rng = np.random.default_rng(10 + n_peers)
    model = NoiseModel(robot, 0.016, 2, 1, 1.0, 5.0, force_std_n=1e-4, torque_std_nm=1e-5,
                       actuation_noise=(0.01, 0.01, 0.001, 0.01), sensor_noise=(1e-2, 1e-3, 1e-3),
                       mismatch_model_std=1e-5)  # fmt: skip
    params = np.array([4.0, 0.1, -0.05, 0.2, 0.3, 0.25, 0.2, 0.01, -0.02, 0.005])
    jac = balance_motion_jacobians(robot, *_motion(rng, robot.n_joints))
    regressor = rng.normal(size=(6, 10))
    peers = []
    for _ in range(n_peers):
        d_links, d_y = balance_motion_jacobians(robot, *_motion(rng, robot.n_joints))
        t = wrench_transform(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 0.5)
        msg = SimpleNamespace(grasp_acc=rng.normal(size=3), motion_links_jac=d_links,
                              motion_grasp_jac=grasp_acc_map(d_y), motion_var=model.motion.var,
                              motion_band=model.motion.band)  # fmt: skip
        peers.append((t, msg))
    mean, cov = model.motion_noise(fusion, params, jac, regressor, peers, 0.3)
    ref_mean, ref_cov = _reference_motion_noise(model, params, jac, regressor, peers, fusion)
    np.testing.assert_allclose(
        mean, ref_mean, rtol=0, atol=1e-9 * max(np.abs(ref_mean).max(), 1e-30)
    )
    np.testing.assert_allclose(cov, ref_cov, rtol=0, atol=1e-12 * np.abs(ref_cov).max())
    assert np.abs(ref_cov).max() > 0
    if fusion == "team" and n_peers:
        assert np.abs(ref_mean).max() > 0
        bad = SimpleNamespace(**{**vars(peers[0][1]), "motion_var": np.ones(3)})
        with pytest.raises(ValueError, match="variances"):
            model.motion_noise(fusion, params, jac, regressor, [(peers[0][0], bad)], 0.3)
        with pytest.raises(ValueError, match="shapes"):
            model.motion_noise(fusion, params, jac, regressor[:3], peers, 0.3)
        bad = SimpleNamespace(**{**vars(peers[0][1]), "grasp_acc": np.ones(2)})
        with pytest.raises(ValueError, match="shapes"):
            model.motion_noise(fusion, params, jac, regressor, [(peers[0][0], bad)], 0.3)


def test_instant_noise_modes_are_the_modes_of_their_parts():
    """``chain_modes.instant_noise_modes`` (one compiled call per update instant) equals its parts:
    the drifting Jacobian's modes (``momentum_noise_modes``) with the gyro's and the
    accelerometer's own factors, then one mode per squared-rate term, sqrt(v_k) (Q_links,
    M_Q Q_Y), or as many zero columns without terms."""
    import scipy.linalg

    from astrocargo.estimator.chain_modes import (
        drifting_sample_jacobian,
        instant_noise_modes,
        momentum_noise_modes,
    )
    from astrocargo.estimator.momentum import CARGO_Q, CARGO_Q_MAP, LINKS_Q, SIZE

    robot = _robot()
    nj = robot.n_joints
    rng = np.random.default_rng(5)
    state = rng.normal(size=(3, 12 + nj)) * 0.3
    arrays, imu_pos = robot.arrays, np.ascontiguousarray(robot.imu_pos, dtype=float)
    gyro, accel, point = rng.normal(size=(4, 4)), rng.normal(size=(4, 4)), rng.normal(size=(8, 8))
    factors = np.ascontiguousarray(np.stack([gyro] * 3 + [accel] * 3))
    n_rate = nj * (nj + 1) // 2
    terms, var = rng.normal(size=(n_rate, SIZE)), rng.uniform(0.5, 2.0, n_rate)
    links, y = instant_noise_modes(arrays, imu_pos, state, nj, 0.05, factors, point, terms, var,
                                   n_rate)  # fmt: skip
    jac, jac_rate = drifting_sample_jacobian(arrays, imu_pos, state, nj, 0.05)
    cols_links, cols_y = momentum_noise_modes(jac, jac_rate, nj)
    factor = scipy.linalg.block_diag(*([gyro] * 3 + [accel] * 3 + [point] * nj))
    n = factor.shape[0]
    scale = np.abs(cols_links).max() * np.abs(factor).max()
    np.testing.assert_allclose(links[:, :n], cols_links @ factor, rtol=0, atol=1e-12 * scale)
    ref_y = np.einsum("kab,km->mab", cols_y, factor)
    np.testing.assert_allclose(y[:n], ref_y, rtol=0, atol=1e-12 * np.abs(ref_y).max())
    scaled = terms * np.sqrt(var)[:, None]
    np.testing.assert_array_equal(links[:, n:], scaled[:, LINKS_Q].T)
    np.testing.assert_allclose(y[n:], (scaled[:, CARGO_Q] @ CARGO_Q_MAP.T).reshape(-1, 6, 10),
                               rtol=1e-12, atol=0)  # fmt: skip
    links0, y0 = instant_noise_modes(arrays, imu_pos, state, nj, 0.05, factors, point,
                                     np.zeros((0, SIZE)), np.zeros(0), n_rate)  # fmt: skip
    np.testing.assert_array_equal(links0[:, :n], links[:, :n])
    assert links0.shape == links.shape and not links0[:, n:].any() and not y0[n:].any()


def test_posterior_spread_is_the_sum_over_modes():
    """``motion.posterior_spread`` (compiled) is sum_k level_k dY_k P dY_k^T over the first n
    levels, exactly symmetric."""
    from astrocargo.estimator.motion import posterior_spread

    rng = np.random.default_rng(6)
    d_y, level = rng.normal(size=(7, 6, 10)), rng.uniform(0.1, 2.0, 9)
    root = rng.normal(size=(10, 10))
    cov = root @ root.T
    ref = sum(level[k] * d_y[k] @ cov @ d_y[k].T for k in range(7))
    spread = posterior_spread(d_y, level, cov)
    np.testing.assert_allclose(spread, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_array_equal(spread, spread.T)


def test_gain_of_solves_where_the_floor_bounds_the_eigenvalues_else_pinv():
    """``motion.gain_of``: K = C A^+ for A = B + floor I; by Cholesky where floor is far above
    pinv's cut (equal to C pinv(A) to rounding: cond(A) eps), by ``pinv_symmetric`` where it
    is not (no floor, or one under the cut, on a singular B: C pinv(A) bit for bit)."""
    from astrocargo.estimator.motion import gain_of

    rng = np.random.default_rng(8)
    for n, floor in ((3, 1e-3), (21, 1e-2), (21, 1e-7), (21, 0.0), (5, 1e-18)):
        root = rng.normal(size=(n, max(n - 2, 1)))  # B singular: rank n - 2
        sym = root @ root.T + floor * np.eye(n)
        cross = rng.normal(size=(6, n))
        expected = cross @ pinv_symmetric(sym)
        gain = gain_of(cross, sym, floor)
        if floor > 1e-13 * np.trace(sym):
            scale = 1e-14 * np.linalg.cond(sym) * np.abs(expected).max()
            np.testing.assert_allclose(gain, expected, rtol=0, atol=scale)
            assert not np.array_equal(gain, expected)  # the solve, not the pseudo-inverse
        else:
            np.testing.assert_array_equal(gain, expected)


def test_relative_grasp_transform_follows_each_new_fix():
    """``RelativeGrasp.transform`` is made again when a fix is added (its average moves), is the
    same object between fixes, and cannot be written."""
    from astrocargo.estimator.messages import RelativeGrasp

    rng = np.random.default_rng(7)
    rel = RelativeGrasp()
    for count in range(1, 4):
        rel.rot_sum += exp_so3(rng.normal(size=3) * 0.05)
        rel.pos_sum += np.array([0.5, 0.0, 0.0]) + rng.normal(size=3) * 0.01
        rel.count = count
        first = rel.transform()
        u, _, vt = np.linalg.svd(rel.rot_sum)
        rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        np.testing.assert_allclose(first, wrench_transform(rot, rel.pos_sum / count), atol=1e-12)
        assert rel.transform() is first and not first.flags.writeable


def test_process_returns_early_only_when_nothing_can_change(monkeypatch):
    """``CargoEstimator.process`` returns at once when no instant or message arrived and nothing
    leaves the history: a flight where it runs in full at every step ends at the same estimates
    and counters, bit for bit."""
    from astrocargo.envs import astrobee_cargo_v0
    from astrocargo.estimator.per_step import EstimatorInputs

    def fly():
        env = astrobee_cargo_v0.parallel_env(n_robots=2, noise="nominal", max_cycles=100000)
        env.reset(seed=3)
        for k in range(400):
            env.step({a: 0.3 * np.sin(0.05 * k + np.arange(8)) for a in env.agents})
        return [(e.ukf.x.copy(), e.ukf.P.copy(), e.counters) for e in env.sim.estimators]

    gated = fly()
    monkeypatch.setattr(EstimatorInputs, "_expiring", lambda self: True)
    full = fly()
    assert sum(c["updates"] for _, _, c in gated) > 0
    for (x, cov, counters), (x_ref, cov_ref, counters_ref) in zip(gated, full, strict=True):
        np.testing.assert_array_equal(x, x_ref)
        np.testing.assert_array_equal(cov, cov_ref)
        assert counters == counters_ref


def test_process_gives_up_instants_and_messages_at_the_same_step_as_a_full_pass(monkeypatch):
    """Over a late and lossy channel (instants given up, messages held and dropped),
    ``process``'s early return (``_expiring`` against the oldest pending stamp) leaves every
    robot's counters equal, step by step, to a flight where it runs in full at every step."""
    from astrocargo.envs import astrobee_cargo_v0
    from astrocargo.estimator.per_step import EstimatorInputs

    def fly():
        env = astrobee_cargo_v0.parallel_env(
            n_robots=3, noise="nominal", max_cycles=100000, comm_latency=0.05, comm_drop=0.3
        )
        env.reset(seed=5)
        seen = []
        for k in range(600):
            *_, infos = env.step({a: 0.3 * np.sin(0.05 * k + np.arange(8)) for a in env.agents})
            seen.append([infos[a]["estimator"] for a in env.possible_agents])
        return seen, [e.ukf.x.copy() for e in env.sim.estimators]

    gated, x_gated = fly()
    monkeypatch.setattr(EstimatorInputs, "_expiring", lambda self: True)
    full, x_full = fly()
    assert sum(c["skipped_missing"] for c in gated[-1]) > 0
    assert sum(c["updates"] for c in gated[-1]) > 0
    assert gated == full
    for x, x_ref in zip(x_gated, x_full, strict=True):
        np.testing.assert_array_equal(x, x_ref)
