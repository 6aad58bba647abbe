"""The cargo's inertial parameters: the arguments that fix or bound them, validated against the
bag the team carries, and the draw at each reset (the env docstring's Arguments and Starting
State sections). Units: kg, m, kg m^2; the centre of mass and the inertia tensor (about the
centre of mass) in the cargo frame."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from astrocargo.envs.config import CARGO_MASS_LIMITS_KG
from astrocargo.envs.validation import check_finite_array, check_finite_number
from astrocargo.envs.world import World
from astrocargo.estimator.inertia import (
    check_physical,
    params_from_mass_com_inertia,
    vec_to_inertia,
)

CARGO_COM_SPREAD_M = 0.03  # sampled centre of mass: uniform in +-this per axis


def _mass_range(mass_kg: Any) -> np.ndarray:
    low_kg, high_kg = CARGO_MASS_LIMITS_KG
    allowed = f"a mass in [{low_kg}, {high_kg}] kg, or a range (low, high) within it"
    if isinstance(mass_kg, tuple | list | np.ndarray):
        bounds = check_finite_array("cargo_mass_kg", mass_kg, (2,), allowed)
    else:
        bounds = np.full(2, check_finite_number("cargo_mass_kg", mass_kg, allowed))
    if not low_kg <= bounds[0] <= bounds[1] <= high_kg:
        raise ValueError(f"cargo_mass_kg must be {allowed}, low <= high, got {mass_kg!r}")
    return bounds


def _com(com_m: Any, half_box: np.ndarray) -> np.ndarray | None:
    if com_m is None:
        return None
    allowed = f"None or 3 numbers (m) within the bag, |c| <= {tuple(half_box)}"
    com = check_finite_array("cargo_com_m", com_m, (3,), allowed)
    if np.any(np.abs(com) > half_box):
        raise ValueError(f"cargo_com_m must be {allowed}, got {com_m!r}")
    return com


def _inertia(inertia: Any, min_mass_kg: float, diagonal_m: float) -> np.ndarray | None:
    """The tensor, realisable about the centre of mass whatever the mass, and with no principal
    moment above m d^2 (no mass farther than the bag's diagonal d from an axis through it)."""
    if inertia is None:
        return None
    allowed = (
        "None or 6 finite numbers (I_xx, I_yy, I_zz, I_xy, I_xz, I_yz) about the centre of mass"
    )
    tensor = vec_to_inertia(check_finite_array("cargo_inertia", inertia, (6,), allowed))
    try:
        check_physical(params_from_mass_com_inertia(1.0, np.zeros(3), tensor))
    except ValueError as err:
        raise ValueError(f"cargo_inertia is not a physical inertia tensor: {err}") from err
    max_moment = min_mass_kg * diagonal_m**2
    if np.linalg.eigvalsh(tensor)[-1] > max_moment:
        raise ValueError(
            f"cargo_inertia: a principal moment exceeds m * d^2 = {max_moment:.3g} kg m^2 "
            f"(mass {min_mass_kg} kg within the bag, diagonal d = {diagonal_m:.3f} m), "
            f"got {inertia!r}"
        )
    return tensor


@dataclass(frozen=True)
class CargoDraw:
    """How the cargo is drawn at each reset: the mass uniform in ``mass_range_kg``; the centre
    of mass ``com_m`` or uniform in +-``CARGO_COM_SPREAD_M``; the inertia ``inertia`` or that of
    a uniform box of the bag's size and the drawn mass."""

    mass_range_kg: np.ndarray
    com_m: np.ndarray | None
    inertia: np.ndarray | None

    @classmethod
    def from_args(cls, world: World, mass_kg: Any, com_m: Any, inertia: Any) -> CargoDraw:
        """Validated against ``world``'s bag (``ValueError``): the centre of mass within it."""
        bounds = _mass_range(mass_kg)
        diagonal_m = math.hypot(*world.cargo_size_m)
        return cls(
            bounds,
            _com(com_m, 0.5 * world.cargo_size_m),
            _inertia(inertia, float(bounds[0]), diagonal_m),
        )

    def sample(
        self, rng: np.random.Generator, world: World
    ) -> tuple[float, np.ndarray, np.ndarray]:
        """Mass (kg), centre of mass (3,) and inertia about it (3, 3), cargo frame."""
        low, high = self.mass_range_kg
        mass = float(rng.uniform(low, high)) if high > low else float(low)
        if self.com_m is None:
            com = rng.uniform(-CARGO_COM_SPREAD_M, CARGO_COM_SPREAD_M, 3)
        else:
            com = self.com_m.copy()
        inertia = world.uniform_cargo_inertia(mass) if self.inertia is None else self.inertia.copy()
        return mass, com, inertia
