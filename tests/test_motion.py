"""The balance's motion noise and its conditioning on the team's IMUs (estimator/motion.py)."""

import numpy as np
import pytest

from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.motion import (
    balance_noise_map,
    condition_on_mismatch,
    grasp_acc_map,
    motion_jacobians,
)
from astrocargo.estimator.rne import (
    balance_in_grasp_frame,
    balance_motion_jacobians,
    links_and_regressor,
)


def test_motion_jacobians_of_an_affine_balance_are_exact():
    rng = np.random.default_rng(0)
    m_links, c_links = rng.normal(size=(6, 8)), rng.normal(size=6)
    m_y, c_y = rng.normal(size=(8, 6, 10)), rng.normal(size=(6, 10))

    def balance(xi):
        return m_links @ xi + c_links, np.einsum("kij,k->ij", m_y, xi) + c_y

    d_links, d_y = motion_jacobians(balance, rng.normal(size=8))
    np.testing.assert_allclose(d_links, m_links, atol=1e-12)
    np.testing.assert_allclose(d_y, m_y, atol=1e-12)
    pi = rng.normal(size=10)
    np.testing.assert_allclose(
        balance_noise_map(d_links, d_y, pi), m_links + np.einsum("kij,j->ik", m_y, pi), atol=1e-12
    )
    point = rng.normal(size=3)
    expected = m_y[:, :3, 0].T + np.einsum("kij,j->ik", m_y[:, :3, 1:4], point)
    np.testing.assert_allclose(grasp_acc_map(d_y, point), expected, atol=1e-12)


def _robot():
    from astrocargo.envs.world import World

    return World(n_robots=1).robot_model(0)


def test_rne_motion_jacobians_are_the_balance_s_unit_differences():
    """rne.balance_motion_jacobians against unit steps of links_and_regressor (an independent
    path through the public API), at a tumbling, bending motion; links_and_regressor is the
    balance's links and regressor."""
    robot = _robot()
    rng = np.random.default_rng(3)
    nj = robot.n_joints
    w, wd, acc = rng.normal(size=3) * 0.3, rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.05
    q, qd, qdd = rng.normal(size=nj) * 0.5, rng.normal(size=nj) * 0.1, rng.normal(size=nj) * 0.1

    def balance(xi):
        return links_and_regressor(robot, w, xi[3:6], xi[0:3], q, qd, xi[6:])

    xi = np.concatenate((acc, wd, qdd))
    d_links, d_y = balance_motion_jacobians(robot, w, wd, acc, q, qd, qdd)
    ref_links, ref_y = motion_jacobians(balance, xi)
    np.testing.assert_allclose(d_links, ref_links, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(d_y, ref_y, rtol=1e-9, atol=1e-12)
    # Affine: the Jacobians predict a finite step exactly.
    step = rng.normal(size=xi.size)
    links0, y0 = balance(xi)
    links1, y1 = balance(xi + step)
    np.testing.assert_allclose(links1, links0 + d_links @ step, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(y1, y0 + np.einsum("kij,k->ij", d_y, step), rtol=1e-9, atol=1e-12)
    full, _, _ = balance_in_grasp_frame(robot, w, wd, acc, q, qd, qdd, np.zeros(6))
    np.testing.assert_array_equal(full.links, links0)
    np.testing.assert_array_equal(full.regressor, y0)


def test_two_accelerometers_on_one_body_leave_the_common_error():
    """n = m1 a1 + m2 a2 with a_k = a + e_k; d = a2 - a1 = e2 - e1 (no truth). Given d, the
    errors' mean (e1 + e2) / 2 remains: Cov[n | d] = (m1 + m2)^2 s^2 / 2 (equal variances),
    against (m1^2 + m2^2) s^2 without the peer's reading."""
    m1, m2, s2 = 15.0, 10.0, 1e-8
    noise6 = [np.vstack([m * np.eye(3), np.zeros((3, 3))]) for m in (m1, m2)]
    var = [np.full(3, s2), np.full(3, s2)]
    alone_mean, alone = condition_on_mismatch(noise6, [], var, None)
    np.testing.assert_allclose(alone_mean, 0.0)
    np.testing.assert_allclose(alone[:3, :3], (m1**2 + m2**2) * s2 * np.eye(3))
    d = np.array([1e-4, -2e-4, 3e-4])
    mean, cov = condition_on_mismatch(noise6, [-np.eye(3), np.eye(3)], var, d)
    np.testing.assert_allclose(cov[:3, :3], (m1 + m2) ** 2 * s2 / 2 * np.eye(3), rtol=1e-12)
    # e1 = c - d / 2, e2 = c + d / 2 with c the common part: E[n | d] = (m2 - m1) d / 2.
    np.testing.assert_allclose(mean[:3], (m2 - m1) * d / 2, rtol=1e-12)


def test_conditioning_matches_regression_on_samples():
    """The Gaussian conditional equals the least-squares regression of n on d over samples."""
    rng = np.random.default_rng(1)
    noise = [rng.normal(size=(6, 8)), rng.normal(size=(6, 8))]
    mism = [rng.normal(size=(3, 8)), rng.normal(size=(3, 8))]
    var = [rng.uniform(0.5, 2.0, 8), rng.uniform(0.5, 2.0, 8)]
    xi = [rng.normal(size=(200_000, 8)) * np.sqrt(v) for v in var]
    n = sum(x @ m.T for x, m in zip(xi, noise, strict=True))
    d = sum(x @ m.T for x, m in zip(xi, mism, strict=True))
    gain = np.linalg.lstsq(d, n, rcond=None)[0].T
    resid = n - d @ gain.T
    d0 = d[0]
    mean, cov = condition_on_mismatch(noise, mism, var, d0)
    np.testing.assert_allclose(mean, gain @ d0, atol=0.02 * np.abs(gain @ d0).max() + 1e-3)
    np.testing.assert_allclose(cov, np.cov(resid.T), atol=0.02 * np.abs(cov).max())


def test_perfect_sensors_give_no_motion_noise():
    mean, cov = condition_on_mismatch(
        [np.ones((6, 8))], [np.ones((3, 8))], [np.zeros(8)], np.zeros(3)
    )
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(cov, 0.0)


def test_bad_shapes_and_modes_raise():
    with pytest.raises(ValueError, match="variances"):
        condition_on_mismatch([np.ones((6, 8))], [], [np.ones(7)], None)
    with pytest.raises(ValueError, match="mismatch"):
        condition_on_mismatch([np.ones((6, 8))], [np.ones((3, 8))], [np.ones(8)], np.zeros(2))
    with pytest.raises(ValueError, match="vector"):
        motion_jacobians(lambda x: (x, x), np.zeros((2, 2)))


def test_motion_fusion_is_validated():
    robot = _robot()
    assert CargoEstimator(robot, 0, [], 0.016).motion_fusion == "team"
    with pytest.raises(ValueError, match="motion_fusion"):
        CargoEstimator(robot, 0, [], 0.016, motion_fusion="peers")


@pytest.mark.parametrize("noise", ["ideal", "nominal"])
def test_team_fusion_in_the_env(noise):
    """Two robots with motion_fusion='team': messages carry the motion, the measurement
    covariance has the motion's force-moment structure, and with perfect sensors the grasp
    accelerations of the two robots agree (the cargo is rigid: the transport is right)."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(
        n_robots=2,
        trajectory="figure8_tumble",
        noise=noise,
        max_cycles=int(12 * 62.5),
        estimator_kwargs={"record": True},
    )
    obs, _ = env.reset(seed=0)
    ctl = ObservationController.for_env(env, "estimate")
    est = env.sim.estimators[0]
    seen = []
    original = est._balance_terms

    def spy(inst, msgs, params):
        out = original(inst, msgs, params)
        seen.append((inst, msgs, out))
        return out

    est._balance_terms = spy
    while env.agents:
        actions, _ = ctl.predict(obs)
        obs, *_ = env.step(actions)
    assert est.counters["updates"] > 0 and seen
    inst, msgs, (_, _, modes, mean, cov) = seen[-1]
    # The known grasp layout takes the one compiled call, which gives this robot's modes too.
    assert modes is not None and modes.shape == (6, inst.motion_jac[1].shape[0])
    # The momentum chain's noise modes, sent as the 9 that carry their links' and grasp
    # acceleration's joint covariance (``NoiseModel.message_modes``).
    assert msgs[0].grasp_acc is not None and msgs[0].motion_links_jac.shape == (6, 9)
    rel = est._relative[est.peers[0]].transform()
    rot = rel[:3, :3]
    lever = rel[3:, :3] @ rot.T
    pos = np.array([lever[2, 1], lever[0, 2], lever[1, 0]])
    mismatch = rot @ msgs[0].grasp_acc - (inst.regressor[:3, 0] + inst.regressor[:3, 1:4] @ pos)
    acc = np.linalg.norm(inst.regressor[:3, 0])
    if noise == "ideal":
        assert np.linalg.norm(mismatch) < 0.02 * acc
        np.testing.assert_array_equal(cov, 0.0)
    else:
        # Force-moment correlation of the motion noise (a diagonal model would have none).
        corr = cov[:3, 3:] / np.sqrt(np.outer(np.diag(cov)[:3], np.diag(cov)[3:]))
        assert np.abs(corr).max() > 0.3
        assert np.all(np.isfinite(est.params_mean()))
    env.close()


def test_team_fusion_three_robots_with_latency_and_drops():
    """Each peer's mismatch is one block row: three robots, a late and lossy channel."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(
        n_robots=3,
        trajectory="figure8_tumble",
        noise="nominal",
        max_cycles=int(8 * 62.5),
        comm_latency=0.1,
        comm_drop=0.2,
    )
    obs, _ = env.reset(seed=1)
    ctl = ObservationController.for_env(env, "estimate")
    while env.agents:
        actions, _ = ctl.predict(obs)
        obs, *_ = env.step(actions)
    for est in env.sim.estimators:
        assert est.counters["updates"] > 0
        assert np.all(np.isfinite(est.params_mean()))
    env.close()
