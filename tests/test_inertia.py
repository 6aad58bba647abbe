"""Tests of astrocargo.estimator.inertia against the log-Cholesky map written out (Rucker and
Wensing 2022) and first principles."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from astrocargo.estimator.inertia import (
    InertialParams,
    check_physical,
    com_error_m,
    errors_given_true,
    estimate_errors,
    inertia_to_vec,
    log_cholesky_jacobian,
    log_cholesky_to_params,
    mass_com_inertia_from_params,
    mass_rel_error,
    params_from_mass_com_inertia,
    params_to_log_cholesky,
    params_to_pseudo_inertia,
    physical_violation,
    principal_moments,
    principal_rel_errors,
    pseudo_inertia_distance,
    pseudo_inertia_to_params,
    pseudo_inertia_transform,
    transform_params,
    true_principal_moments,
    vec_to_inertia,
)

ROUND_TRIP_TOL = 1e-10
BATCH_SHAPES = [(), (21,), (4, 5)]


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Uniformly random proper rotations of shape (*shape, 3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=shape + (3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    q[..., :, 0] *= np.sign(np.linalg.det(q))[..., None]
    return q


def random_bodies(
    rng: np.random.Generator, shape: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random realisable bodies: mass 0.1-20 kg, com within 0.5 m, rotated principal moments.

    The principal moments come from positive principal second moments s_i (kg m^2) as
    I_1 = s_2 + s_3 and so on, which is exactly the set that satisfies the triangle inequality.
    """
    mass_kg = rng.uniform(0.1, 20.0, size=shape)
    direction = rng.normal(size=shape + (3,))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    com_m = direction * 0.5 * rng.uniform(0.0, 1.0, size=shape + (1,)) ** (1 / 3)
    second_moments = mass_kg[..., None] * rng.uniform(0.05, 0.5, size=shape + (3,)) ** 2
    moments = second_moments.sum(axis=-1, keepdims=True) - second_moments
    rotation = random_rotations(rng, shape)
    inertia_com = rotation @ (moments[..., :, None] * np.swapaxes(rotation, -1, -2))
    inertia_com = 0.5 * (inertia_com + np.swapaxes(inertia_com, -1, -2))
    return mass_kg, com_m, inertia_com


def random_params(rng: np.random.Generator, shape: tuple[int, ...] = ()) -> np.ndarray:
    return params_from_mass_com_inertia(*random_bodies(rng, shape))


def params_by_equations_md(eta: np.ndarray) -> np.ndarray:
    """log-Cholesky -> pi written out term by term from the published map, for one eta."""
    alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3 = eta
    m = np.exp(2 * alpha)
    e1, e2, e3 = np.exp([d1, d2, d3])
    return m * np.array(
        [
            1.0,
            t1,
            t2,
            t3,
            s23**2 + t2**2 + t3**2 + e2**2 + e3**2,
            s12**2 + s13**2 + t1**2 + t3**2 + e1**2 + e3**2,
            s12**2 + s13**2 + s23**2 + t1**2 + t2**2 + e1**2 + e2**2,
            -s12 * e2 - s13 * s23 - t1 * t2,
            -s13 * e3 - t1 * t3,
            -s23 * e3 - t2 * t3,
        ]
    )


def point_mass_params(masses_kg: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """pi of point masses as direct sums: h = sum m x, I_o = sum m (|x|^2 1 - x x^T)."""
    h = masses_kg @ points_m
    inertia_o = sum(
        m * (x @ x * np.eye(3) - np.outer(x, x)) for m, x in zip(masses_kg, points_m, strict=True)
    )
    return np.concatenate(
        [
            [masses_kg.sum()],
            h,
            [inertia_o[0, 0], inertia_o[1, 1], inertia_o[2, 2]],
            [inertia_o[0, 1], inertia_o[0, 2], inertia_o[1, 2]],
        ]
    )


# --------------------------------------------------------------------------- small helpers


def test_inertia_vector_order_and_round_trip():
    inertia = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    np.testing.assert_array_equal(inertia_to_vec(inertia), [1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(vec_to_inertia(inertia_to_vec(inertia)), inertia)


def test_inertia_to_vec_rejects_asymmetric_tensor():
    with pytest.raises(ValueError, match="symmetric"):
        inertia_to_vec(np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))


# --------------------------------------------------------------------------- log-Cholesky


def test_params_to_log_cholesky_round_trip():
    rng = np.random.default_rng(2)
    pi = random_params(rng, (200,))
    np.testing.assert_allclose(
        log_cholesky_to_params(params_to_log_cholesky(pi)), pi, rtol=0, atol=ROUND_TRIP_TOL
    )


def test_log_cholesky_to_params_round_trip():
    rng = np.random.default_rng(3)
    eta = rng.normal(scale=1.0, size=(200, 10))
    np.testing.assert_allclose(
        params_to_log_cholesky(log_cholesky_to_params(eta)), eta, rtol=0, atol=ROUND_TRIP_TOL
    )


def test_log_cholesky_matches_equations_md_and_upper_factor():
    rng = np.random.default_rng(4)
    for eta in rng.normal(size=(20, 10)):
        alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3 = eta
        upper = np.exp(alpha) * np.array(
            [
                [np.exp(d1), s12, s13, t1],
                [0.0, np.exp(d2), s23, t2],
                [0.0, 0.0, np.exp(d3), t3],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        pi = log_cholesky_to_params(eta)
        np.testing.assert_allclose(pi, params_by_equations_md(eta), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(params_to_pseudo_inertia(pi), upper @ upper.T, atol=1e-12)
        np.testing.assert_allclose(pi[1:4] / pi[0], [t1, t2, t3], atol=1e-13)


def test_log_cholesky_jacobian_matches_central_differences():
    rng = np.random.default_rng(5)
    eta = rng.normal(size=(30, 10))
    step = 1e-6
    numeric = np.stack(
        [
            (log_cholesky_to_params(eta + step * e) - log_cholesky_to_params(eta - step * e))
            / (2 * step)
            for e in np.eye(10)
        ],
        axis=-1,
    )
    analytic = log_cholesky_jacobian(eta)
    scale = np.abs(analytic).max(axis=(-2, -1), keepdims=True)
    assert (np.abs(analytic - numeric) / scale).max() < 1e-6


# Mathematically every real eta is realisable. In float64 the check needs the smallest eigenvalue
# of J well above round-off (~1e-16 of the largest): with d and s down to -5 and +-5, J can be
# singular to machine precision (eta = (0, -5, ..., -5) gives min/max eigenvalue ~5e-20), so d and
# s stay within +-3 (min/max >= ~7e-14); alpha and t (mass e^+-10 kg, com up to 5 m) use +-5.
ETA_BOUNDS = np.array([5.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0, 5.0, 5.0, 5.0])


@settings(max_examples=500, deadline=None)
@given(arrays(np.float64, 10, elements=st.floats(-1.0, 1.0)))
def test_every_bounded_eta_is_a_realisable_body(unit_eta):
    pi = log_cholesky_to_params(ETA_BOUNDS * unit_eta)
    assert physical_violation(pi) is None
    assert np.linalg.eigvalsh(params_to_pseudo_inertia(pi)).min() > 0.0


def test_params_to_log_cholesky_rejects_inconsistent_body():
    pi = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    with pytest.raises(ValueError, match="triangle inequality"):
        params_to_log_cholesky(pi)


# --------------------------------------------------------------------------- physical consistency


def test_check_example_breaks_triangle_inequality():
    pi = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    message = physical_violation(pi)
    assert message is not None
    assert "principal moments 1, 1, 2.5 break the triangle inequality 1 + 1 >= 2.5" in message
    assert np.linalg.eigvalsh(params_to_pseudo_inertia(pi)).min() < 0.0
    with pytest.raises(ValueError, match="triangle inequality"):
        check_physical(pi)


@pytest.mark.parametrize("mass_kg", [0.0, -1.5])
def test_non_positive_mass_is_named_first(mass_kg):
    # This inertia also breaks the triangle inequality: the mass must be reported first.
    pi = params_from_mass_com_inertia(mass_kg, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    with pytest.raises(ValueError, match="mass must be positive"):
        check_physical(pi)


def test_inertia_not_positive_definite_is_named():
    pi = params_from_mass_com_inertia(1.0, np.array([0.1, 0.0, 0.0]), np.diag([1.0, 1.0, -0.5]))
    with pytest.raises(
        ValueError, match="inertia about the centre of mass must be positive definite"
    ):
        check_physical(pi)


def test_flat_plate_is_caught_by_the_pseudo_inertia():
    # I_1 + I_2 = I_3 holds with equality: a plate of zero thickness, J singular.
    pi = params_from_mass_com_inertia(1.0, np.zeros(3), np.diag([1.0, 1.0, 2.0]))
    message = physical_violation(pi)
    assert message is not None and "pseudo-inertia must be positive definite" in message


def test_tol_demands_a_margin():
    pi = params_from_mass_com_inertia(1.0, np.zeros(3), np.diag([0.01, 1.0, 1.0]))
    assert physical_violation(pi) is None
    assert "positive definite" in physical_violation(pi, tol=0.1)
    with pytest.raises(ValueError, match="tol"):
        physical_violation(pi, tol=-1.0)


def test_batch_violation_names_first_bad_index():
    rng = np.random.default_rng(6)
    pi = random_params(rng, (3, 4))
    assert physical_violation(pi) is None
    pi[1, 2] = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    pi[2, 0, 0] = -1.0
    message = physical_violation(pi)
    assert "(1, 2)" in message and "triangle inequality" in message


def test_random_bodies_are_consistent():
    rng = np.random.default_rng(7)
    assert physical_violation(random_params(rng, (500,))) is None


# --------------------------------------------------------------------------- standard parameters


def test_parallel_axis_equals_point_mass_sums():
    rng = np.random.default_rng(8)
    masses_kg = rng.uniform(0.5, 3.0, size=5)
    points_m = rng.normal(scale=0.4, size=(5, 3)) + np.array([0.3, -0.2, 0.1])
    pi_direct = point_mass_params(masses_kg, points_m)

    mass_kg = masses_kg.sum()
    com_m = masses_kg @ points_m / mass_kg
    offsets = points_m - com_m
    inertia_com = sum(
        mi * (ri @ ri * np.eye(3) - np.outer(ri, ri))
        for mi, ri in zip(masses_kg, offsets, strict=True)
    )
    np.testing.assert_allclose(
        params_from_mass_com_inertia(mass_kg, com_m, inertia_com), pi_direct, atol=1e-12
    )
    mass_back, com_back, inertia_back = mass_com_inertia_from_params(pi_direct)
    np.testing.assert_allclose(mass_back, mass_kg, rtol=1e-14)
    np.testing.assert_allclose(com_back, com_m, atol=1e-14)
    np.testing.assert_allclose(inertia_back, inertia_com, atol=1e-12)
    assert physical_violation(pi_direct) is None


def test_product_of_inertia_sign_convention():
    # One point mass at (1, 1, 0): I_xy = -m x y.
    pi = point_mass_params(np.array([2.0]), np.array([[1.0, 1.0, 0.0]]))
    assert pi[7] == pytest.approx(-2.0)
    # A point mass m at x has J = m [x; 1] [x; 1]^T.
    x_hom = np.array([1.0, 1.0, 0.0, 1.0])
    np.testing.assert_allclose(params_to_pseudo_inertia(pi), 2.0 * np.outer(x_hom, x_hom))


def test_pseudo_inertia_round_trip_and_definition():
    rng = np.random.default_rng(9)
    pi = random_params(rng, (10,))
    j = params_to_pseudo_inertia(pi)
    np.testing.assert_allclose(pseudo_inertia_to_params(j), pi, atol=1e-13)
    inertia_o = vec_to_inertia(pi[..., 4:])
    trace = np.trace(inertia_o, axis1=-2, axis2=-1)
    np.testing.assert_allclose(
        j[..., :3, :3], 0.5 * trace[..., None, None] * np.eye(3) - inertia_o, atol=1e-14
    )
    np.testing.assert_allclose(j[..., :3, 3], pi[..., 1:4])
    np.testing.assert_allclose(j[..., 3, :3], pi[..., 1:4])
    np.testing.assert_allclose(j[..., 3, 3], pi[..., 0])


def test_mass_com_inertia_from_params_rejects_zero_mass():
    with pytest.raises(ValueError, match="mass must be positive"):
        mass_com_inertia_from_params(np.zeros(10))


def test_principal_moments_sorted():
    rng = np.random.default_rng(10)
    rotation = random_rotations(rng, ())
    inertia = rotation @ np.diag([3.0, 1.0, 2.5]) @ rotation.T
    np.testing.assert_allclose(principal_moments(inertia), [1.0, 2.5, 3.0], atol=1e-13)


# --------------------------------------------------------------------------- frame changes


def test_transform_params_matches_transform_by_hand():
    rng = np.random.default_rng(11)
    mass_kg, com_a, inertia_com_a = random_bodies(rng, (25,))
    rotation = random_rotations(rng, (25,))
    translation_m = rng.normal(size=(25, 3))
    pi_b = transform_params(
        params_from_mass_com_inertia(mass_kg, com_a, inertia_com_a), rotation, translation_m
    )
    com_b = (rotation @ com_a[..., None])[..., 0] + translation_m
    inertia_com_b = rotation @ inertia_com_a @ np.swapaxes(rotation, -1, -2)
    inertia_com_b = 0.5 * (inertia_com_b + np.swapaxes(inertia_com_b, -1, -2))
    np.testing.assert_allclose(
        pi_b, params_from_mass_com_inertia(mass_kg, com_b, inertia_com_b), atol=1e-12
    )


def test_transform_params_composes():
    rng = np.random.default_rng(12)
    pi_a = random_params(rng, (10,))
    r_ab, r_bc = random_rotations(rng, (2, 10))
    p_ab, p_bc = rng.normal(size=(2, 10, 3))
    pi_c = transform_params(transform_params(pi_a, r_ab, p_ab), r_bc, p_bc)
    # x_C = r_bc (r_ab x_A + p_ab) + p_bc
    r_ac = r_bc @ r_ab
    p_ac = (r_bc @ p_ab[..., None])[..., 0] + p_bc
    np.testing.assert_allclose(transform_params(pi_a, r_ac, p_ac), pi_c, atol=1e-12)
    # and back again
    np.testing.assert_allclose(
        transform_params(
            pi_c, np.swapaxes(r_ac, -1, -2), -(np.swapaxes(r_ac, -1, -2) @ p_ac[..., None])[..., 0]
        ),
        pi_a,
        atol=1e-12,
    )


def test_transform_broadcasts_one_body_over_many_frames():
    rng = np.random.default_rng(13)
    pi = random_params(rng)
    rotation = random_rotations(rng, (6,))
    translation_m = rng.normal(size=(6, 3))
    batched = transform_params(pi, rotation, translation_m)
    assert batched.shape == (6, 10)
    for k in range(6):
        np.testing.assert_allclose(
            batched[k], transform_params(pi, rotation[k], translation_m[k]), atol=1e-14
        )
    j = params_to_pseudo_inertia(pi)
    np.testing.assert_allclose(
        pseudo_inertia_transform(j, rotation, translation_m),
        params_to_pseudo_inertia(batched),
        atol=1e-12,
    )


def test_transform_rejects_non_rotation():
    pi = random_params(np.random.default_rng(14))
    with pytest.raises(ValueError, match="rotation"):
        transform_params(pi, 2.0 * np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="rotation"):
        transform_params(pi, np.diag([1.0, 1.0, -1.0]), np.zeros(3))


# --------------------------------------------------------------------------- error metrics


def test_error_metrics_on_known_differences():
    pi_true = params_from_mass_com_inertia(2.0, np.array([0.1, 0.0, 0.0]), np.diag([1.0, 2.0, 2.5]))
    pi_est = params_from_mass_com_inertia(2.5, np.array([0.1, 0.3, 0.4]), np.diag([1.1, 1.8, 2.5]))
    assert mass_rel_error(pi_est, pi_true) == pytest.approx(0.25)
    assert com_error_m(pi_est, pi_true) == pytest.approx(0.5)
    np.testing.assert_allclose(principal_rel_errors(pi_est, pi_true), [0.1, 0.1, 0.0], atol=1e-12)
    assert mass_rel_error(pi_true, pi_true) == 0.0


def test_estimate_errors_equal_the_three_metrics_batched():
    rng = np.random.default_rng(18)
    pi_est, pi_true = random_params(rng, (2, 5))
    mass, com, principal = estimate_errors(pi_est, pi_true)
    np.testing.assert_array_equal(mass, mass_rel_error(pi_est, pi_true))
    np.testing.assert_array_equal(com, com_error_m(pi_est, pi_true))
    np.testing.assert_array_equal(principal, principal_rel_errors(pi_est, pi_true))
    bad = pi_est.copy()
    bad[2, 0] = -1.0
    with pytest.raises(ValueError, match="pi_est must have positive mass"):
        estimate_errors(bad, pi_true)
    # One true body against the batch (broadcast), as the separate metrics do.
    for got, want in zip(
        estimate_errors(pi_est, pi_true[1]),
        (f(pi_est, pi_true[1]) for f in (mass_rel_error, com_error_m, principal_rel_errors)),
        strict=True,
    ):
        np.testing.assert_array_equal(got, want)
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="pi_est must be finite"):
        estimate_errors(bad, pi_true)
    flat = pi_true.copy()
    flat[1, 4:] = 0.0  # zero inertia about the origin: a moment about the com is negative
    with pytest.raises(ValueError, match="pi_true must have positive principal moments"):
        estimate_errors(pi_est, flat)


def test_errors_given_true_equal_estimate_errors():
    """The refresh's path (true principal moments computed once) gives ``estimate_errors``'s
    values bit for bit, and the same ValueErrors."""
    rng = np.random.default_rng(19)
    pi_est, pi_true = (a.reshape(-1, 10) for a in random_params(rng, (2, 6)))
    moments = true_principal_moments(pi_true)
    out = np.empty((6, 5))
    errors_given_true(pi_est, pi_true, moments, out)
    mass, com, principal = estimate_errors(pi_est, pi_true)
    np.testing.assert_array_equal(out, np.column_stack((mass, com, principal)))
    bad = pi_est.copy()
    bad[2, 0] = -1.0
    with pytest.raises(ValueError, match="pi_est must have positive mass"):
        errors_given_true(bad, pi_true, moments, out)
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="pi_est must be finite"):
        errors_given_true(bad, pi_true, moments, out)
    flat = pi_true.copy()
    flat[1, 4:] = 0.0
    with pytest.raises(ValueError, match="pi_true must have positive principal moments"):
        true_principal_moments(flat)


def test_pseudo_inertia_distance_is_frame_free():
    rng = np.random.default_rng(15)
    pi_a, pi_b = random_params(rng, (2, 12))
    rotation = random_rotations(rng, (12,))
    translation_m = rng.normal(size=(12, 3))
    distance = pseudo_inertia_distance(pi_a, pi_b)
    assert (distance > 0.0).all()
    moved = pseudo_inertia_distance(
        transform_params(pi_a, rotation, translation_m),
        transform_params(pi_b, rotation, translation_m),
    )
    np.testing.assert_allclose(moved, distance, rtol=1e-9)
    np.testing.assert_allclose(pseudo_inertia_distance(pi_b, pi_a), distance, rtol=1e-9)
    np.testing.assert_allclose(pseudo_inertia_distance(pi_a, pi_a), 0.0, atol=1e-7)


def test_pseudo_inertia_distance_of_scaled_mass():
    # Scaling the whole body by k scales J by k: four eigenvalues k, distance 2 |log k|.
    pi = random_params(np.random.default_rng(16))
    assert pseudo_inertia_distance(pi, 3.0 * pi) == pytest.approx(2.0 * np.log(3.0))


def test_pseudo_inertia_distance_rejects_inconsistent_body():
    good = random_params(np.random.default_rng(17))
    bad = params_from_mass_com_inertia(2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]))
    for a, b in [(good, bad), (bad, good)]:
        with pytest.raises(ValueError, match="triangle inequality"):
            pseudo_inertia_distance(a, b)


# --------------------------------------------------------------------------- batches and inputs


def _batched_cases(rng: np.random.Generator, shape: tuple[int, ...]):
    pi = random_params(rng, shape)
    pi_other = random_params(rng, shape)
    eta = rng.normal(size=shape + (10,))
    rotation = random_rotations(rng, shape)
    translation_m = rng.normal(size=shape + (3,))
    inertia = vec_to_inertia(pi[..., 4:])
    return {
        "log_cholesky_to_params": (log_cholesky_to_params, (eta,)),
        "params_to_log_cholesky": (params_to_log_cholesky, (pi,)),
        "log_cholesky_jacobian": (log_cholesky_jacobian, (eta,)),
        "params_to_pseudo_inertia": (params_to_pseudo_inertia, (pi,)),
        "pseudo_inertia_to_params": (pseudo_inertia_to_params, (params_to_pseudo_inertia(pi),)),
        "transform_params": (transform_params, (pi, rotation, translation_m)),
        "principal_moments": (principal_moments, (inertia,)),
        "inertia_to_vec": (inertia_to_vec, (inertia,)),
        "vec_to_inertia": (vec_to_inertia, (pi[..., 4:],)),
        "mass_rel_error": (mass_rel_error, (pi, pi_other)),
        "com_error_m": (com_error_m, (pi, pi_other)),
        "principal_rel_errors": (principal_rel_errors, (pi, pi_other)),
        "pseudo_inertia_distance": (pseudo_inertia_distance, (pi, pi_other)),
        "mass_com_inertia_from_params": (mass_com_inertia_from_params, (pi,)),
    }


@pytest.mark.parametrize("shape", BATCH_SHAPES)
@pytest.mark.parametrize("name", list(_batched_cases(np.random.default_rng(0), ()).keys()))
def test_batches_equal_per_element_results(name, shape):
    function, args = _batched_cases(np.random.default_rng(18), shape)[name]
    batched = function(*args)
    outputs = batched if isinstance(batched, tuple) else (batched,)
    for index in np.ndindex(shape):
        single = function(*(a[index] for a in args))
        singles = single if isinstance(single, tuple) else (single,)
        for out, one in zip(outputs, singles, strict=True):
            assert out.shape[: len(shape)] == shape
            np.testing.assert_allclose(out[index], one, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    ("function", "arg", "match"),
    [
        (log_cholesky_to_params, np.zeros(9), r"shape \(\.\.\., 10\)"),
        (params_to_log_cholesky, np.zeros((3, 11)), r"shape \(\.\.\., 10\)"),
        (params_to_pseudo_inertia, np.zeros((4, 4)), r"shape \(\.\.\., 10\)"),
        (pseudo_inertia_to_params, np.zeros(10), r"shape \(\.\.\., 4, 4\)"),
        (principal_moments, np.zeros((3, 2)), r"shape \(\.\.\., 3, 3\)"),
        (log_cholesky_to_params, np.r_[np.zeros(9), np.nan], "finite"),
        (log_cholesky_jacobian, np.r_[np.zeros(9), np.inf], "finite"),
        (physical_violation, np.r_[1.0, np.zeros(8), np.nan], "finite"),
    ],
)
def test_bad_inputs_raise_value_error(function, arg, match):
    with pytest.raises(ValueError, match=match):
        function(arg)


# --------------------------------------------------------------------------- InertialParams


def test_inertial_params_round_trips():
    rng = np.random.default_rng(19)
    mass_kg, com_m, inertia_com = random_bodies(rng)
    body = InertialParams(mass_kg, com_m, inertia_com)
    pi = params_from_mass_com_inertia(mass_kg, com_m, inertia_com)
    np.testing.assert_allclose(body.to_vector(), pi)
    np.testing.assert_allclose(body.pseudo_inertia(), params_to_pseudo_inertia(pi))
    np.testing.assert_allclose(body.to_log_cholesky(), params_to_log_cholesky(pi))
    again = InertialParams.from_vector(pi)
    assert again.mass == pytest.approx(mass_kg)
    np.testing.assert_allclose(again.com, com_m, atol=1e-14)
    np.testing.assert_allclose(again.inertia_com, inertia_com, atol=1e-12)
    from_eta = InertialParams.from_log_cholesky(body.to_log_cholesky())
    np.testing.assert_allclose(from_eta.to_vector(), pi, atol=1e-12)
    np.testing.assert_allclose(body.principal_moments(), principal_moments(inertia_com))
    assert InertialParams(mass_kg, com_m, inertia_com) == body


def test_inertial_params_transformed_matches_transform_params():
    rng = np.random.default_rng(20)
    body = InertialParams(*random_bodies(rng))
    rotation = random_rotations(rng, ())
    translation_m = rng.normal(size=3)
    np.testing.assert_allclose(
        body.transformed(rotation, translation_m).to_vector(),
        transform_params(body.to_vector(), rotation, translation_m),
        atol=1e-12,
    )


def test_inertial_params_is_immutable_copy():
    com_m = np.array([0.1, 0.0, 0.0])
    inertia_com = np.diag([1.0, 2.0, 2.5])
    body = InertialParams(2.0, com_m, inertia_com)
    com_m[0] = 5.0
    inertia_com[0, 0] = 9.0
    assert body.com[0] == 0.1 and body.inertia_com[0, 0] == 1.0
    with pytest.raises(ValueError):
        body.com[0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        body.mass = 3.0


@pytest.mark.parametrize(
    ("mass_kg", "com_m", "inertia_com", "match"),
    [
        (2.0, np.zeros(3), np.diag([1.0, 1.0, 2.5]), "triangle inequality"),
        (0.0, np.zeros(3), np.eye(3), "mass must be positive"),
        (1.0, np.zeros(3), np.diag([1.0, 1.0, -1.0]), "positive definite"),
        (1.0, np.zeros(2), np.eye(3), r"shape \(3,\)"),
        (1.0, np.zeros(3), np.eye(2), r"shape \(3, 3\)"),
        (1.0, np.zeros((2, 3)), np.eye(3), r"shape \(3,\)"),
        (np.ones(2), np.zeros(3), np.eye(3), "scalar"),
        (1.0, np.array([0.0, np.nan, 0.0]), np.eye(3), "finite"),
    ],
)
def test_inertial_params_validation(mass_kg, com_m, inertia_com, match):
    with pytest.raises(ValueError, match=match):
        InertialParams(mass_kg, com_m, inertia_com)
