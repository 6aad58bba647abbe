"""The records that carry a step's arrays into the compiled kernels (``estimator.records``),
the readings cut from blocks of them (``envs.sensors.FreshReadings``) and the estimator's
constants as one record (``estimator.per_step.estimator_constants``)."""

import copy
import pickle

import numpy as np
import pytest

from astrocargo.envs.sensors import FreshReadings, SensorReadings
from astrocargo.estimator.records import as_interned, bound_views, interned, record_of


def test_record_fields_are_views_and_bools_round_trip():
    rot = np.arange(9.0).reshape(3, 3)
    mask = np.array([True, False, True])
    record = record_of({"rot": rot, "mask": mask, "rows": np.array([4, 7])})
    views = bound_views(record)
    np.testing.assert_array_equal(views["rot"], rot)
    assert views["mask"].dtype == np.bool_
    np.testing.assert_array_equal(views["mask"], mask)
    views["rot"][1, 2] = -1.0
    views["mask"][1] = True
    assert record["rot"][0][1, 2] == -1.0
    assert record["mask"][0][1] == 1
    assert rot[1, 2] == 5.0  # the record holds a copy


def test_record_refuses_scalars_and_uint8():
    with pytest.raises(ValueError, match="at least one dimension"):
        record_of({"dt_s": np.float64(0.1)})
    with pytest.raises(ValueError, match="uint8"):
        record_of({"flags": np.zeros(3, dtype=np.uint8)})


def test_equal_layouts_share_one_dtype_object():
    a = record_of({"x": np.zeros(3), "y": np.zeros((2, 2))})
    b = record_of({"x": np.ones(3), "y": np.ones((2, 2))})
    assert a.dtype is b.dtype
    unpickled = pickle.loads(pickle.dumps(a))
    assert unpickled.dtype == a.dtype
    again = as_interned(unpickled)
    assert again.dtype is interned(a.dtype)
    assert np.shares_memory(again, unpickled)


def test_fresh_readings_are_distinct_views_of_their_records():
    fresh = FreshReadings(2, block=3)
    got = [fresh() for _ in range(7)]  # three blocks
    for readings, record in got:
        assert isinstance(readings, SensorReadings)
        readings.accel_imu[1] = [1.0, 2.0, 3.0]
        readings.has_fix[0] = True
        np.testing.assert_array_equal(record["accel"][0][1], [1.0, 2.0, 3.0])
        assert record["has_fix"][0][0] == 1
    first, second = got[0][0], got[1][0]
    first.gyro_imu[0, 0] = 9.0
    assert second.gyro_imu[0, 0] == 0.0
    twin = copy.deepcopy(fresh)
    readings, record = twin()
    readings.joint_pos_rad[0, 1] = 0.5
    assert record["joints"][0][0, 1] == 0.5


def test_estimator_constants_hold_the_step_constants():
    from astrocargo.envs.world import World
    from astrocargo.estimator.cargo_estimator import CargoEstimator
    from astrocargo.estimator.per_step import CONSTANT_FIELDS

    est = CargoEstimator(World(1).robot_model(0), 0, [], 0.016)
    constants = est._step_constants[0]
    np.testing.assert_array_equal(constants["parent"], est.robot.arrays.parent)
    assert constants["grasp_link"][0] == est.robot.arrays.grasp_link
    assert constants["dt_s"][0] == est.dt_s
    assert est._step_constants.dtype.names == CONSTANT_FIELDS
    twin = pickle.loads(pickle.dumps(est))
    assert twin._step_constants.dtype is est._step_constants.dtype
