"""Arrays bound once as one record, so that a compiled kernel takes them as one argument.

numba checks and unboxes every argument of every call, which for the few robots of a step
costs more than the arithmetic; a NumPy record of a structured dtype with one field per array
is unboxed in one check, and inside the kernel ``rec[0].name`` is the same array as before.

- ``record_of`` builds such a record (shape (1,)) from named arrays, its dtype ``interned``;
- ``bound_views`` gives the fields back as views, so the Python code that writes an array in
  place writes the record the kernel reads.

numba's records hold no booleans: a bool array is stored as uint8 (0 or 1; the kernel reads
and writes it as numbers) and viewed back as bool.
"""

from __future__ import annotations

import functools

import numpy as np


def record_of(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """A record (shape (1,)) with one field per entry of ``arrays`` (name -> array, of at least
    one dimension: a 0-d field reads back as a copy, not a view), holding a copy of each."""
    for name, value in arrays.items():
        if np.ndim(value) == 0:
            raise ValueError(f"field {name!r} must be an array of at least one dimension")
    dtype = interned(
        np.dtype([(name, _stored(value.dtype), value.shape) for name, value in arrays.items()])
    )
    record = np.zeros(1, dtype=dtype)
    for name, value in arrays.items():
        record[name][0] = value
    return record


@functools.cache
def interned(dtype: np.dtype) -> np.dtype:
    """The first dtype built equal to ``dtype``: numba's dispatch recognises a structured dtype
    quickly only by identity (an equal one built anew takes its slow path at every call)."""
    return dtype


def as_interned(record: np.ndarray) -> np.ndarray:
    """``record`` viewed with its dtype ``interned`` (an unpickled record has a new one)."""
    return record.view(interned(record.dtype))


def bound_views(record: np.ndarray) -> dict[str, np.ndarray]:
    """Each field of ``record`` (``record_of``) as a view: writing one writes the record."""
    return {
        name: record[name][0].view(np.bool_) if stored_bool else record[name][0]
        for name, stored_bool in _fields(record.dtype)
    }


@functools.cache
def _fields(dtype: np.dtype) -> tuple[tuple[str, bool], ...]:
    """Each field's name and whether it holds a bool array (stored as uint8)."""
    return tuple((name, dtype.fields[name][0].base == np.uint8) for name in dtype.names)


def _stored(dtype: np.dtype) -> np.dtype:
    """The field type of an array of ``dtype``: uint8 for bool, else itself; a uint8 array
    would read back as bool, so it is refused."""
    if dtype == np.uint8:
        raise ValueError("uint8 arrays are not allowed in a record (bool arrays are stored so)")
    return np.dtype(np.uint8) if dtype == np.bool_ else dtype
