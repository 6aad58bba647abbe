"""The team's refresh and peer slots (``envs.estimation``): the compiled, in-place paths give
the per-robot composition's values (bit for bit where the arithmetic is the same, at rounding
where a product is regrouped)."""

import numpy as np
import pytest

from astrocargo.envs import astrobee_cargo_v0
from astrocargo.estimator.encoder_covariance import sandwich, sandwich_std
from astrocargo.estimator.inertia import estimate_errors


def test_sandwich_std_is_the_sandwichs_diagonal():
    """sqrt(diag(P + P X P)) without the full product, for a contiguous P and a strided one."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(10, 10))
    P = a @ a.T + 0.1 * np.eye(10)
    b = rng.normal(size=(10, 10))
    # The cross terms lower the spread, as the encoders' do: P + P X P = 0.6 P + 1e-4 P B B^T P.
    X = -0.4 * np.linalg.inv(P) + 1e-4 * (b @ b.T)
    expected = np.sqrt(np.diag(sandwich(P, X)))
    assert np.all(np.isfinite(expected)) and np.all(expected < np.sqrt(np.diag(P)))
    out = np.empty(10)
    sandwich_std(P, X, out)
    np.testing.assert_allclose(out, expected, rtol=1e-13)
    wide = np.zeros((10, 20))
    wide[:, ::2] = P
    sandwich_std(wide[:, ::2], X, out)
    np.testing.assert_allclose(out, expected, rtol=1e-13)


@pytest.fixture(scope="module")
def flown_team():
    env = astrobee_cargo_v0.parallel_env(n_robots=3, noise="nominal")
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    for _ in range(330):
        env.step({a: rng.uniform(-0.3, 0.3, 8) for a in env.agents})
    team = env.sim.estimation
    assert sum(est.ukf.n_updates for est in team.estimators) > 0
    return team


def test_refresh_equals_the_per_robot_composition(flown_team):
    """Means as ``params_mean`` gives them; spreads sqrt(diag(``params_cov``)); errors as
    ``estimate_errors`` gives them; log-std sums as numpy's; new arrays at every call."""
    team = flown_team
    mean, std, errors = team.refresh()
    np.testing.assert_array_equal(mean, [est.params_mean() for est in team.estimators])
    want_std = np.sqrt([np.diag(est.params_cov()) for est in team.estimators])
    np.testing.assert_allclose(std, want_std, rtol=1e-13)
    mass, com, principal = estimate_errors(mean, team.true_params_grasp)
    assert errors == [
        {"mass_rel_err": m, "com_err_m": c, "principal_rel_err": p}
        for m, c, p in zip(mass.tolist(), com.tolist(), principal.tolist(), strict=True)
    ]
    logs = np.log(np.maximum(want_std, 1e-12)).sum(axis=1)
    np.testing.assert_allclose(team.log_std_sums, logs, rtol=1e-13)
    again = team.refresh()
    assert again[0] is not mean and again[1] is not std and again[2][0] is not errors[0]
    np.testing.assert_array_equal(again[1], std)


def test_peer_slots_equal_the_indexing_of_the_latest_messages(flown_team):
    """The compiled peer slots equal the [receiver, slot's sender] indexing of the latest
    messages, masked by stamp >= 0 and ``acting``, for every acting pattern."""
    team = flown_team
    rows = np.arange(3)[:, None]
    team.latest_stamp[2, 0] = -1  # one slot without a message
    for acting in ([1, 1, 1], [1, 0, 1], [0, 0, 0]):
        acting = np.array(acting, dtype=bool)
        stamp, valid, wrench, arrived, arm = team._slot_arrays(acting)
        want_stamp = team.latest_stamp[rows, team.peer_slots]
        want_valid = (want_stamp >= 0) & acting[:, None]
        np.testing.assert_array_equal(stamp, want_stamp)
        np.testing.assert_array_equal(valid, want_valid)
        np.testing.assert_array_equal(arrived, want_valid.astype(float))
        sent = team.latest_wrench[rows, team.peer_slots]
        np.testing.assert_array_equal(wrench, np.where(want_valid[..., None], sent, 0.0))
        sent_arm = team.latest_arm[rows, team.peer_slots]
        np.testing.assert_array_equal(arm, np.where(want_valid[..., None], sent_arm, 0.0))
        assert want_valid.any() == bool(acting.any())
        assert not any(a.flags.writeable for a in (stamp, valid, wrench, arrived, arm))
