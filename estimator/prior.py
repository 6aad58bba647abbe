"""The cargo estimator's prior on the cargo's standard parameters pi (10,) in the grasp frame:
a generic mean (``default_prior``), its covariance from standard deviations of the physical
quantities (``prior_covariance``) and the random walk per update (``DEFAULT_PROCESS_STD_REL``).

pi = [m, h_x, h_y, h_z, I_xx, I_yy, I_zz, I_xy, I_xz, I_yz] (kg, kg m, kg m^2), h = m c, I about
the grasp frame's origin (``estimator.inertia``).
"""

from __future__ import annotations

import functools

import numpy as np

from .inertia import (
    inertia_to_vec,
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    vec_to_inertia,
)
from .rne import RobotDescription

# Prior standard deviations (see `prior_covariance`): mass 3 kg, centre of mass 0.15 m per axis,
# moments of inertia about the centre of mass 0.1 kg m^2, products 0.03 kg m^2: wide for a cargo
# of a few kilograms and tens of centimetres, so the data, not the prior, decide.
DEFAULT_PRIOR_STD = (3.0, 0.15, 0.1, 0.03)

# Random walk of the parameters per update, as a fraction of the prior standard deviations. The
# cargo is rigid and its parameters constant, so none: a walk adds to the filter's covariance
# what the truth never does (earlier versions used 1e-5, with no measurement behind it; where the
# data pin a direction well it made the filter 2.5-13 times too cautious there, see
# docs/estimation_limits.md). A positive value models a cargo whose parameters drift.
DEFAULT_PROCESS_STD_REL = 0.0


def default_prior(robot: RobotDescription) -> np.ndarray:
    """A generic prior in the grasp frame: a 3 kg, 0.3 m cube whose centre is 0.2 m beyond the
    grasp, along -z of the grasp frame (the fingers point along -z, into the cargo)."""
    del robot
    side = 0.3
    mass = 3.0
    return params_from_mass_com_inertia(
        mass, np.array([0.0, 0.0, -0.2]), np.eye(3) * mass * side**2 / 6
    )


def prior_covariance(
    prior_params: np.ndarray,
    std: tuple[float, float, float, float] = DEFAULT_PRIOR_STD,
    step: float = 1e-6,
) -> np.ndarray:
    """Covariance of pi (10, 10) for independent errors of the prior's physical quantities:
    ``std`` = (mass kg, centre of mass m per axis, moments of inertia about the centre of mass
    kg m^2, products of inertia kg m^2), carried to pi = (m, m c, I_origin) through the map's
    Jacobian at ``prior_params`` (central differences)."""
    std = np.asarray(std, dtype=float)
    if std.shape != (4,) or not np.all(np.isfinite(std)) or np.any(std <= 0):
        raise ValueError(f"prior std must be 4 positive numbers (kg, m, kg m^2, kg m^2), got {std}")
    prior_params = np.asarray(prior_params, dtype=float)
    # Every estimator of a team, at every reset, asks for the same one: computed once per value
    # (the arrays as tuples of floats, exact, for the cache's key).
    key = (prior_params.shape, tuple(prior_params.ravel().tolist()), tuple(std.tolist()))
    return _covariance(*key, float(step)).copy()


@functools.lru_cache(maxsize=64)
def _covariance(shape: tuple, prior_params: tuple, std: tuple, step: float) -> np.ndarray:
    """`prior_covariance` of checked arguments (``prior_params`` flattened, of ``shape``); the
    cached result is read-only."""
    prior_params = np.array(prior_params).reshape(shape)
    std = np.array(std)
    mass, com, inertia = mass_com_inertia_from_params(prior_params)
    phys = np.concatenate(([mass], com, inertia_to_vec(inertia)))
    sd = np.repeat(std, (1, 3, 3, 3))
    # Row k of ``probes``: the quantities moved by +step (k < 10) or -step (k >= 10) along k.
    probes = phys + np.concatenate((step * np.eye(10), -step * np.eye(10)))
    params = params_from_mass_com_inertia(
        probes[:, 0], probes[:, 1:4], vec_to_inertia(probes[:, 4:])
    )
    jac = (params[:10] - params[10:]).T / (2 * step)
    cov = (jac * sd**2) @ jac.T
    cov = 0.5 * (cov + cov.T)
    cov.setflags(write=False)
    return cov
