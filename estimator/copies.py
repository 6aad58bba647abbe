"""Deep copies of the estimator's objects (a ``CargoEstimator`` and the filters, models and
records it holds), as ``copy.deepcopy`` makes them, with less of its per-value work.

``copy.deepcopy`` of an object copies its state (``__getstate__``, else its ``__dict__``) as a
dict: every attribute name and every value goes through ``deepcopy``'s dispatch, including
the many ints, floats, strings and flags, which it returns as they are. ``deepcopy_state``,
a class's ``__deepcopy__``, builds the same copy: values of an immutable type are taken as
they are without the dispatch (numpy scalars too, which deepcopy would copy into an equal
immutable scalar), every other value through ``copy.deepcopy`` with the same memo (so shared
and repeated objects stay shared within the copy, as deepcopy keeps them), and the state is
restored through ``__setstate__`` where the class has one, else into the new ``__dict__``.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

# Types whose values are immutable: a copy may take them as they are.
IMMUTABLE_TYPES = frozenset(
    {int, float, bool, complex, str, bytes, type(None), slice, np.float64, np.int64, np.bool_}
)


def deepcopy_state(obj: Any, memo: dict[int, Any]) -> Any:
    """``copy.deepcopy(obj, memo)`` of an object whose state is a dict of its attributes
    (``__getstate__``, else ``__dict__``): a new instance of its class, recorded in ``memo``,
    with each attribute's value deep-copied (immutable ones taken as they are)."""
    cls = type(obj)
    new = cls.__new__(cls)
    memo[id(obj)] = new
    state = {
        name: value if type(value) in IMMUTABLE_TYPES else copy.deepcopy(value, memo)
        for name, value in obj.__getstate__().items()
    }
    if hasattr(new, "__setstate__"):
        new.__setstate__(state)
    else:
        new.__dict__.update(state)
    return new
