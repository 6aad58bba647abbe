"""Small compiled predicates shared by the kernels of every folder."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["all_finite"]


@njit(cache=True)
def all_finite(a: np.ndarray) -> bool:
    """Whether every entry of ``a`` (any shape and layout) is finite, with no temporary
    (unlike ``np.isfinite(a).all()``)."""
    for value in a.flat:
        if not math.isfinite(value):
            return False
    return True
