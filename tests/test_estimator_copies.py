"""The estimator's copy protocol (``estimator.copies.deepcopy_state``, the classes'
``__deepcopy__``) makes the copy ``copy.deepcopy``'s own algorithm makes: the same classes,
the same values bit for bit (arrays: dtype object, shape, strides, flags, bytes), the same
sharing (the robots with the original, any object reached twice reached twice in the copy)."""

from __future__ import annotations

import collections
import copy

import numpy as np
import pytest

from astrocargo.envs import astrobee_cargo_v0
from astrocargo.estimator.copies import deepcopy_state
from astrocargo.estimator.deferred_reports import DeferredReports
from astrocargo.estimator.encoder_covariance import EncoderCovariance
from astrocargo.estimator.messages import RelativeGrasp
from astrocargo.estimator.motion import RegressorAutocorrelation
from astrocargo.estimator.noise_model import MotionNoiseSpec, NoiseModel
from astrocargo.estimator.per_step import EstimatorInputs
from astrocargo.estimator.preprocess import Preprocessor, StateVariableFilter
from astrocargo.estimator.ukf import BatchedUKF


def _stdlib_deepcopy(obj, memo, monkeypatch):
    """``copy.deepcopy`` with every ``__deepcopy__ = deepcopy_state`` removed (its generic
    ``__reduce_ex__`` path), the protocol restored afterwards."""
    with monkeypatch.context() as patch:
        for cls in PROTOCOL_CLASSES:
            patch.delattr(cls, "__deepcopy__")
        return copy.deepcopy(obj, memo)


SCALARS = (int, float, complex, str, bytes, type(None), slice, np.generic)

# The classes whose ``__deepcopy__`` is ``deepcopy_state`` (InertialParamUKF's through
# BatchedUKF, CargoEstimator's through EstimatorInputs).
PROTOCOL_CLASSES = (
    BatchedUKF, DeferredReports, EncoderCovariance, EstimatorInputs, MotionNoiseSpec,
    NoiseModel, Preprocessor, RegressorAutocorrelation, RelativeGrasp, StateVariableFilter,
)  # fmt: skip


def _state(obj) -> dict:
    return dict(vars(obj)) if hasattr(obj, "__dict__") else {}


def _assert_same_copy(a, b, original, pairs: dict[int, int], shared: set[int]) -> None:
    """``a`` (the protocol's copy) and ``b`` (the stdlib's) of ``original`` are alike."""
    assert type(a) is type(b), (type(a), type(b))
    if id(original) in shared:
        assert a is original and b is original
        return
    if isinstance(a, SCALARS):
        assert repr(a) == repr(b)  # floats: the shortest repr that reads back the same bits
        return
    if id(a) in pairs:  # reached before: the same object again in both copies
        assert pairs[id(a)] == id(b)
        return
    pairs[id(a)] = id(b)
    if isinstance(a, np.ndarray):
        assert a.dtype is b.dtype and a.shape == b.shape and a.strides == b.strides
        assert a.flags.writeable == b.flags.writeable
        assert a.tobytes() == b.tobytes()
        assert not np.shares_memory(a, original) or a is original  # a copy, not the original
        return
    if isinstance(a, dict):
        assert list(a) == list(b)
        for key in a:
            _assert_same_copy(a[key], b[key], original[key], pairs, shared)
        return
    if isinstance(a, list | tuple | collections.deque):
        assert len(a) == len(b)
        for x, y, o in zip(a, b, original, strict=True):
            _assert_same_copy(x, y, o, pairs, shared)
        return
    state_a, state_b = _state(a), _state(b)
    assert list(state_a) == list(state_b)
    for name in state_a:
        _assert_same_copy(state_a[name], state_b[name], getattr(original, name), pairs, shared)


@pytest.mark.parametrize("steps", [0, 60])
def test_estimators_copy_as_deepcopy_does(steps, monkeypatch):
    """Unstepped (``FreshEstimators``' built ones) and mid-episode (after updates, messages
    and fixes) estimators: the protocol's copy matches the stdlib algorithm's."""
    env = astrobee_cargo_v0.parallel_env(n_robots=3, noise="nominal", control_hz=12.5)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(steps):
        env.step({agent: 0.3 * rng.uniform(-1, 1, 8) for agent in env.agents})
    sim = env.sim
    estimators = sim.estimators if steps else sim._fresh_estimators._built
    shared = {id(r) for r in sim.robots}
    memo = {id(r): r for r in sim.robots}
    ours = copy.deepcopy(estimators, dict(memo))
    theirs = _stdlib_deepcopy(estimators, dict(memo), monkeypatch)
    assert all(cls.__dict__["__deepcopy__"] is deepcopy_state for cls in PROTOCOL_CLASSES)
    _assert_same_copy(ours, theirs, estimators, {}, shared)
    assert all(est.noise is est._reports.noise for est in ours)  # sharing kept
