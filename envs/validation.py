"""Argument checks shared by the env's configuration and its fault specs: each raises
``ValueError`` naming the argument, what was given and what is allowed."""

from __future__ import annotations

from typing import Any

import numpy as np


def check_finite_number(name: str, value: Any, allowed: str) -> float:
    """``value`` as a float if it is a finite real number (no booleans)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    if not np.isfinite(value):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return float(value)


def check_finite_array(name: str, value: Any, shape: tuple[int, ...], allowed: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (numbers only: no strings, no booleans)."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {allowed}, got {value!r}") from None
    if raw.dtype.kind not in "iuf" or raw.shape != shape or not np.all(np.isfinite(raw)):
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return raw.astype(float)


def check_choice(name: str, value: Any, allowed: Any) -> str:
    """``value`` if it is one of the strings ``allowed``."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; allowed: {sorted(allowed)}")
    return value
