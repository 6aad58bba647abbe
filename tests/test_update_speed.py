"""The compiled per-update kernels (rne._balance_jacobians, motion's conditioning,
noise_model._team_maps) against the plain forms they replace."""

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
