"""Updates conditioned on the previous ones (estimator/over_time.py) and the estimator's option."""

import numpy as np
import pytest

from astrocargo.estimator.motion import kernel_lag_covariances
from astrocargo.estimator.over_time import (
    UpdateWindow,
    cross_covariance,
    mode_lag_covariances,
)

UPDATE = 5  # control steps per update of the synthetic chain


def _synthetic_run(k: int, n_lags: int, seed: int):
    """K updates of a linear Gaussian model z = A pi + e: a held chain's modes Gm from random
    kernels (4, 40), per update a map J (6, 2 channels, 4) and a white rest; the whole-run
    covariance Sigma (6K, 6K) as ``over_time`` writes it, and per update its diagonal block."""
    rng = np.random.default_rng(seed)
    kernels = np.cumsum(rng.normal(size=(4, 8 * UPDATE)), axis=1)[:, ::-1]
    _, gm = mode_lag_covariances(kernel_lag_covariances(kernels, UPDATE, n_lags))
    jac = rng.normal(size=(k, 6, 2, 4))
    root = 0.3 * rng.normal(size=(k, 6, 6))
    rest = root @ root.transpose(0, 2, 1) + 0.05 * np.eye(6)
    sigma = np.zeros((6 * k, 6 * k))
    for i in range(k):
        for m in range(i, min(k, i + n_lags + 1)):
            block = cross_covariance(jac[i], jac[m], gm[m - i])
            sigma[6 * i : 6 * i + 6, 6 * m : 6 * m + 6] = block
            sigma[6 * m : 6 * m + 6, 6 * i : 6 * i + 6] = block.T
        sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += rest[i]
    a = rng.normal(size=(k, 6, 10))
    b = rng.normal(size=(k, 6))
    truth = rng.normal(size=10)
    e = np.linalg.cholesky(sigma) @ rng.normal(size=6 * k)
    z = np.einsum("kij,j->ki", a, truth) + b + e.reshape(k, 6)
    diag = np.stack([sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(k)])
    return gm, jac, diag, sigma, a, b, z


def _sequential(gm, jac, diag, a, b, z, length, skip=()):
    """Information and information vector of the conditioned updates (``UpdateWindow``), the
    updates in ``skip`` left out (not used, so not in the window)."""
    window = UpdateWindow(gm, length, UPDATE)
    info, vec = np.zeros((10, 10)), np.zeros(10)
    for i in range(len(z)):
        if i in skip:
            continue
        (zc, ac, bc, rc), entry = window.condition(i * UPDATE, z[i], a[i], b[i], diag[i], jac[i])
        w = np.linalg.inv(rc)
        info += ac.T @ w @ ac
        vec += ac.T @ w @ (zc - bc)
        window.add(entry)
    return info, vec


def test_mode_lag_covariances_carry_the_kernels_lag_covariances():
    """F Gm(L) F^T = G(L) for the estimator's chain (the modes' covariance over time is the
    kernels'), and Gm(0) = I."""
    from astrocargo.envs.world import World
    from astrocargo.estimator.cargo_estimator import CargoEstimator
    from astrocargo.estimator.motion import HELD_EXTENDED
    from astrocargo.estimator.noise_model import _momentum_chain

    est = CargoEstimator(World(2).robot_model(0), 0, [1], 0.016, over_time_window=8)
    lag_cov = _momentum_chain(*est.noise.chain_args, est.update_every)[2]
    held = lag_cov[:, HELD_EXTENDED][:, :, HELD_EXTENDED]
    factor, gm = mode_lag_covariances(held)
    np.testing.assert_allclose(gm, est.noise.mode_lag_cov)
    np.testing.assert_allclose(gm[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(factor @ gm @ factor.T, held, atol=1e-12 * np.abs(held).max())


def test_window_over_the_whole_run_is_generalised_least_squares():
    """Conditioning each update on all the used ones before it is the whole run's GLS (the
    innovations form of Sigma^-1): the same information A^T Sigma^-1 A and information vector;
    a window shorter than the noise's memory is not (this test can fail)."""
    k, n_lags = 30, 8
    gm, jac, diag, sigma, a, b, z = _synthetic_run(k, n_lags, 1)
    rows = a.reshape(6 * k, 10)
    info = rows.T @ np.linalg.solve(sigma, rows)
    vec = rows.T @ np.linalg.solve(sigma, (z - b).ravel())
    seq_info, seq_vec = _sequential(gm, jac, diag, a, b, z, length=k)
    np.testing.assert_allclose(seq_info, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())
    np.testing.assert_allclose(seq_vec, vec, rtol=1e-8, atol=1e-10 * np.abs(vec).max())
    # The window of the noise's memory: Sigma's blocks beyond it are zero, the conditioning on
    # a Markov-free window is then close but not exact.
    short, _ = _sequential(gm, jac, diag, a, b, z, length=1)
    assert np.abs(short - info).max() > 1e-3 * np.abs(info).max()


def test_skipped_updates_leave_the_window():
    """Updates that are not used (skipped, gated) are not in the window: the conditioned run
    without them is GLS on the used updates' own covariance (exact for the subset)."""
    k, n_lags = 24, 8
    gm, jac, diag, sigma, a, b, z = _synthetic_run(k, n_lags, 2)
    skip = {3, 4, 10}
    used = [i for i in range(k) if i not in skip]
    idx = np.concatenate([np.arange(6 * i, 6 * i + 6) for i in used])
    rows = a[used].reshape(-1, 10)
    info = rows.T @ np.linalg.solve(sigma[np.ix_(idx, idx)], rows)
    seq_info, _ = _sequential(gm, jac, diag, a, b, z, length=k, skip=skip)
    np.testing.assert_allclose(seq_info, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())


def test_rolled_back_entries_are_dropped():
    """``drop_from`` forgets the entries of a stamp and later; a missing IMU map restarts the
    window; a window must hold an update."""
    k, n_lags = 6, 8
    gm, jac, diag, _, a, b, z = _synthetic_run(k, n_lags, 3)
    window = UpdateWindow(gm, 10, UPDATE)
    for i in range(k):
        window.add(window.condition(i * UPDATE, z[i], a[i], b[i], diag[i], jac[i])[1])
    window.drop_from(3 * UPDATE)
    assert [e.stamp for e in window.entries] == [0, UPDATE, 2 * UPDATE]
    (zc, *_), entry = window.condition(9 * UPDATE, z[0], a[0], b[0], diag[0], None)
    assert entry is None and np.array_equal(zc, z[0])
    window.add(entry)
    assert not window.entries
    with pytest.raises(ValueError, match="at least 1"):
        UpdateWindow(gm, 0, UPDATE)


def test_estimator_with_a_window_stays_consistent():
    """Two robots, nominal noise, 30 s of the tumble with ``over_time_window``: every update
    conditioned (the recorded covariance below the update's own at some updates), the estimate
    within 4 of its standard deviations of the truth in every parameter."""
    from test_estimator import simulate

    kwargs = {"record": True, "over_time_window": 24}
    world, estimators = simulate(2, "nominal", 30.0, "figure8_tumble", estimator_kwargs=kwargs)
    for i, est in enumerate(estimators):
        assert est.counters["updates"] > 80
        assert len(est._window.entries) == 24
        truth = world.cargo_params_in_grasp_frame(i)
        z = (est.params_mean() - truth) / est.params_std()
        assert np.all(np.abs(z) < 4.0), z
        own = [e.cov for e in est._window.entries]  # the last used updates, as the log's
        logged = [r for *_, r in est.log[-len(own) :]]
        shrunk = [np.trace(r) < np.trace(c) for r, c in zip(logged, own, strict=True)]
        assert any(shrunk)
    with pytest.raises(ValueError, match="over_time_window"):
        type(est)(world.robot_model(0), 0, [1], 0.016, over_time_window=-1)
