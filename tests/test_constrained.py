"""Tests of estimator.constrained: the compiled barrier method against a plain numpy computation of
the same method (same start, weight schedule, stopping rules and backtracking), on many random
means and covariances: inconsistent means far from and next to the boundary of the consistent set,
with and without a warm start; and its pieces against ``estimator.inertia``'s maps."""

import numpy as np
import pytest

from astrocargo.estimator import constrained
from astrocargo.estimator.constrained import constrained_mode, is_physical
from astrocargo.estimator.inertia import (
    params_from_mass_com_inertia,
    params_to_pseudo_inertia,
    project_physical,
    pseudo_inertia_to_params,
)

RTOL = 1e-10
GAP = 1e-4


def barrier_terms(pi: np.ndarray, directions: np.ndarray):
    """log det J(pi), its gradient tr(J^-1 B_l) and (minus) Hessian tr(J^-1 B_l J^-1 B_m) along
    the directions B_l (n, 4, 4); None where J is not positive definite."""
    j = params_to_pseudo_inertia(pi)
    if np.linalg.eigvalsh(j)[0] <= 0.0:
        return None
    a = np.linalg.solve(j[None], directions)  # A_l = J^-1 B_l
    return np.linalg.slogdet(j)[1], np.trace(a, axis1=1, axis2=2), np.einsum("lij,mji->lm", a, a)


def numpy_mode(mean, cov, start=None, gap=GAP):
    """`constrained_mode` in plain numpy: the consistent mean itself; else the eigenvalue-clipped
    body (``inertia.project_physical``) or a consistent nearer ``start`` as the start, then Newton
    on 0.5 |v|^2 - t log det J(mean + L v) for t = 1 (1e-2 from ``start``), / 50, ... gap / 4,
    each step halved until J stays definite and the Armijo condition holds."""
    if np.linalg.eigvalsh(params_to_pseudo_inertia(mean))[0] > 0.0:
        return mean.copy()
    lower = np.linalg.cholesky(cov)
    directions = params_to_pseudo_inertia(lower.T)  # B_l = J(L e_l)
    v, t = np.linalg.solve(lower, project_physical(mean, min_eig=1e-3) - mean), 1.0
    if start is not None and np.isfinite(start).all() and is_physical(start):
        v_start = np.linalg.solve(lower, start - mean)
        if v_start @ v_start < v @ v:
            v, t = v_start, 1e-2
    terms = barrier_terms(mean + lower @ v, directions)
    while True:
        for _ in range(50):
            log_det, grad_b, hess_b = terms
            gradient = v - t * grad_b
            step = -np.linalg.solve(np.eye(10) + t * hess_b, gradient)
            decrement = -gradient @ step
            if decrement < 0.1 * gap:
                break
            for scale in 0.5 ** np.arange(40):
                trial = v + scale * step
                trial_terms = barrier_terms(mean + lower @ trial, directions)
                if trial_terms is not None and (
                    0.5 * trial @ trial - t * trial_terms[0]
                    <= 0.5 * v @ v - t * log_det - 0.25 * scale * decrement
                ):
                    v, terms = trial, trial_terms
                    break
            else:
                break
        if 4.0 * t <= gap:
            return mean + lower @ v
        t = max(t / 50.0, 0.25 * gap)


def random_body(rng: np.random.Generator) -> np.ndarray:
    """A consistent body: 1-8 kg, centre of mass within 1.5 m of the origin, rotated principal
    moments from a box of random sides (a thin one included)."""
    sides = rng.uniform(0.02, 0.6, 3)
    moments = (sides[[1, 0, 0]] ** 2 + sides[[2, 2, 1]] ** 2) / 12.0
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    mass = rng.uniform(1.0, 8.0)
    inertia = mass * (q * moments) @ q.T
    return params_from_mass_com_inertia(mass, rng.uniform(-1.5, 1.5, 3), inertia)


def pushed_out(body: np.ndarray, depth: float, rng: np.random.Generator) -> np.ndarray:
    """A body ``depth`` (a fraction of J's largest eigenvalue) outside the consistent set: ``body``
    with J's least eigenvalue set to 0 (a point of the boundary), then moved out along that
    eigenvector (or a random direction), J - depth lambda_max u u^T."""
    j = params_to_pseudo_inertia(body)
    lam, vec = np.linalg.eigh(j)
    u = vec[:, 0] if rng.uniform() < 0.7 else vec @ rng.normal(size=4)
    u /= np.linalg.norm(u)
    j_out = j - lam[0] * np.outer(vec[:, 0], vec[:, 0]) - depth * lam[-1] * np.outer(u, u)
    return pseudo_inertia_to_params(0.5 * (j_out + j_out.T))


def random_cov(rng: np.random.Generator, body: np.ndarray) -> np.ndarray:
    """Covariance of random axes whose largest standard deviation is 1e-4 to 1e-1 of the body's
    largest parameter, condition number up to 100."""
    q, _ = np.linalg.qr(rng.normal(size=(10, 10)))
    std = np.abs(body).max() * 10.0 ** rng.uniform(-4.0, -1.0)
    return (q * std**2 * 10.0 ** rng.uniform(-2.0, 0.0, 10)) @ q.T


CASES = [(seed, depth) for seed in range(30) for depth in (1e-6, 1e-5, 1e-4, 1e-3)]


@pytest.mark.parametrize(("seed", "depth"), CASES)
def test_mode_equals_a_plain_numpy_barrier(seed, depth):
    """Next to the boundary (depth 1e-6 of J's largest eigenvalue) and far from it (1e-3: the
    mode up to some 30 standard deviations away), cold and warm started: the compiled method
    returns the plain computation's body to 1e-10."""
    rng = np.random.default_rng(seed)
    body = random_body(rng)
    mean, cov = pushed_out(body, depth, rng), random_cov(rng, body)
    assert not is_physical(mean)
    cold, solved = constrained_mode(mean, cov)
    assert solved and is_physical(cold)
    np.testing.assert_allclose(cold, numpy_mode(mean, cov), rtol=0, atol=RTOL * np.abs(cold).max())
    # Warm: the previous mode of a mean that moved a little, as the filter calls it.
    moved = mean + np.linalg.cholesky(cov) @ rng.normal(scale=0.1, size=10)
    warm, solved = constrained_mode(moved, cov, start=cold)
    expected = numpy_mode(moved, cov, start=cold)
    assert solved
    np.testing.assert_allclose(warm, expected, rtol=0, atol=RTOL * np.abs(expected).max())


def test_warm_start_is_taken_only_when_nearer_and_consistent():
    """A start farther than the clipped body, an inconsistent one and a non-finite one are all
    ignored: the mode is the cold one, bit for bit."""
    rng = np.random.default_rng(7)
    body = random_body(rng)
    mean, cov = pushed_out(body, 1e-2, rng), random_cov(rng, body)
    cold, _ = constrained_mode(mean, cov)
    far = mean + 1e3 * np.sqrt(np.diag(cov))
    far = far if is_physical(far) else project_physical(far, min_eig=0.1)
    for start in (far, pushed_out(random_body(rng), 0.1, rng), np.full(10, np.nan), None):
        np.testing.assert_array_equal(constrained_mode(mean, cov, start=start)[0], cold)
    nearer, _ = constrained_mode(mean + 1e-3 * np.sqrt(np.diag(cov)), cov)
    warm, _ = constrained_mode(mean, cov, start=nearer)
    np.testing.assert_allclose(warm, numpy_mode(mean, cov, start=nearer), rtol=0, atol=1e-10)
    assert not np.array_equal(warm, cold)  # the path, hence where it stops, depends on the start


def test_consistent_mean_is_its_own_mode_and_inputs_are_checked():
    rng = np.random.default_rng(3)
    body = random_body(rng)
    cov = random_cov(rng, body)
    mode, solved = constrained_mode(body, cov)
    assert solved and mode is not body
    np.testing.assert_array_equal(mode, body)
    with pytest.raises(ValueError, match="finite array of shape"):
        constrained_mode(np.full(10, np.nan), cov)
    with pytest.raises(ValueError, match="finite array of shape"):
        constrained_mode(body[:9], cov)
    with pytest.raises(ValueError, match="cov must have shape"):
        constrained_mode(pushed_out(body, 0.1, rng), cov[:9, :9])
    with pytest.raises(ValueError, match="gap must be positive"):
        constrained_mode(body, cov, gap=0.0)


@pytest.mark.parametrize("seed", range(20))
def test_compiled_pieces_equal_the_inertia_maps(seed):
    """J(pi), pi(J), the eigenvalue clipping and the barrier's derivatives of the compiled kernels
    against ``estimator.inertia`` and the definitions tr(A_l), tr(A_l A_m) with A_l = J^-1 B_l."""
    rng = np.random.default_rng(100 + seed)
    body = random_body(rng)
    outside = pushed_out(body, 10.0 ** rng.uniform(-6, 0), rng)
    j = np.empty((4, 4))
    constrained._pseudo_inertia_into(outside, j)
    scale = np.abs(outside).max()
    np.testing.assert_allclose(j, params_to_pseudo_inertia(outside), rtol=0, atol=1e-15 * scale)
    pi = np.empty(10)
    constrained._params_into(j, pi)
    np.testing.assert_allclose(pi, outside, rtol=0, atol=1e-15 * scale)
    np.testing.assert_allclose(
        constrained._clipped_body(outside, 1e-3),
        project_physical(outside, min_eig=1e-3),
        rtol=0,
        atol=1e-12 * scale,
    )
    lower = np.linalg.cholesky(random_cov(rng, body))
    directions = params_to_pseudo_inertia(lower.T)
    grad, hess = np.empty(10), np.empty((10, 10))
    work = np.empty((4, 4)), np.empty((4, 4)), np.empty((10, 10))
    constrained._barrier_derivatives(
        np.linalg.cholesky(params_to_pseudo_inertia(body)), directions, *work, grad, hess
    )
    _, grad_ref, hess_ref = barrier_terms(body, directions)
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-10, atol=1e-12 * np.abs(grad_ref).max())
    np.testing.assert_allclose(hess, hess_ref, rtol=1e-10, atol=1e-12 * np.abs(hess_ref).max())
