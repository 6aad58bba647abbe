"""The peers' packed message buffers (``WrenchMessage.packed``) and their unpacking in the
compiled instant (``instant_terms.unpack_peers``, ``packed_instant_terms``): the same arrays,
bit for bit, as stacking the messages' fields."""

import numpy as np
import pytest

from astrocargo.envs.comms import freeze_arrays
from astrocargo.estimator.instant_terms import (
    instant_terms_kernel,
    packed_instant_terms,
    unpack_peers,
)
from astrocargo.estimator.messages import WrenchMessage


def _message(rng, sender: int, n: int, **changes) -> WrenchMessage:
    cov = rng.normal(size=(6, 6))
    fields = {
        "wrench_grasp": rng.normal(size=6),
        "wrench_cov_grasp": cov @ cov.T,
        "grasp_acc": rng.normal(size=3),
        "motion_links_jac": rng.normal(size=(6, n)),
        "motion_grasp_jac": rng.normal(size=(3, n)),
        "motion_var": rng.uniform(0.1, 1.0, n),
        "motion_band": rng.uniform(0.1, 1.0, n),
        **changes,
    }
    return WrenchMessage(
        sender, 0, wrench_world=rng.normal(size=6), grasp_pos_world=np.zeros(3),
        grasp_rot_world=np.eye(3), fix=False, **fields,
    )  # fmt: skip


def _stacks(msgs):
    """The peers' arrays stacked as ``instant_terms_kernel`` takes them, field by field."""
    return (
        np.concatenate([m.motion_var for m in msgs]),
        np.concatenate([m.motion_band for m in msgs]),
        np.concatenate([m.motion_links_jac for m in msgs], axis=1),
        np.concatenate([m.motion_grasp_jac for m in msgs], axis=1),
        np.array([m.grasp_acc for m in msgs]),
        np.array([m.wrench_grasp for m in msgs]),
        np.array([m.wrench_cov_grasp for m in msgs]),
    )


@pytest.mark.parametrize("sizes", [(), (4,), (3, 5, 4), (7,) * 7])
def test_unpacking_gives_the_stacked_fields(sizes):
    rng = np.random.default_rng(len(sizes))
    msgs = [_message(rng, k + 1, n) for k, n in enumerate(sizes)]
    starts = np.array([0, *np.cumsum(sizes, dtype=np.int64)], dtype=np.int64)
    packed = np.concatenate([m.packed() for m in msgs]) if msgs else np.zeros(0)
    got = unpack_peers(packed, starts)
    expected = _stacks(msgs) if msgs else None
    for k, array in enumerate(got):
        if expected is None:
            assert array.size == 0
            continue
        assert array.shape == expected[k].shape
        assert np.array_equal(array, expected[k])


def test_packed_instant_terms_is_the_kernel_on_the_stacks():
    """Three peers of different sizes: the packed path's five results equal, bit for bit, those
    of ``instant_terms_kernel`` on the fields stacked one by one."""
    rng = np.random.default_rng(7)
    n_own, sizes = 5, (3, 5, 4)
    msgs = [_message(rng, k + 1, n) for k, n in enumerate(sizes)]
    starts = np.array([0, *np.cumsum(sizes)], dtype=np.int64)
    spread = rng.normal(size=(10, 10))
    own = (rng.uniform(0.1, 1.0, n_own), rng.uniform(0.1, 1.0, n_own))
    shared = (
        rng.normal(size=10), rng.normal(size=(6, n_own)), rng.normal(size=(n_own, 6, 10)),
        rng.normal(size=(6, 10)), rng.normal(size=(len(sizes), 6, 6)),
    )  # fmt: skip
    tail = (0.3 * np.eye(6), 0.01 * np.eye(6), 10.0, rng.normal(size=6))  # act, floor, every, links
    for condition in (False, True):
        var, band, links, grasp, acc, wrenches, covs = _stacks(msgs)
        expected = instant_terms_kernel(
            *shared, links, grasp, acc, starts, (own[0], var), (own[1], band), condition, 0.02,
            spread @ spread.T, True, tail[0], wrenches, covs, *tail[1:],
        )  # fmt: skip
        got = packed_instant_terms(
            *shared, np.concatenate([m.packed() for m in msgs]), starts, *own, condition, 0.02,
            spread @ spread.T, True, *tail,
        )  # fmt: skip
        for g, e in zip(got, expected, strict=True):
            assert np.array_equal(g, e)
        assert np.all(np.isfinite(got[1]))


def test_a_message_packs_its_fields_in_order_and_keeps_them_once_frozen():
    rng = np.random.default_rng(3)
    msg = _message(rng, 1, 4)
    packed = msg.packed()
    parts = (msg.motion_var, msg.motion_band, msg.motion_links_jac, msg.motion_grasp_jac,
             msg.grasp_acc, msg.wrench_grasp, msg.wrench_cov_grasp)  # fmt: skip
    assert np.array_equal(packed, np.concatenate([p.ravel() for p in parts]))
    msg.wrench_grasp[0] += 1.0  # writable: packed anew, so it follows the fields
    assert msg.packed()[11 * 4 + 3] == msg.wrench_grasp[0]
    assert msg.packed() is not msg.packed()
    freeze_arrays(msg)  # read-only: packed once
    assert msg.packed() is msg.packed()
    assert np.array_equal(msg.packed(), np.concatenate([p.ravel() for p in parts]))


def test_a_message_without_matching_motion_arrays_has_no_buffer():
    rng = np.random.default_rng(4)
    assert _message(rng, 1, 3, motion_var=None).packed() is None
    assert _message(rng, 1, 3, motion_var=np.ones(4)).packed() is None
    assert _message(rng, 1, 3, motion_grasp_jac=np.ones((3, 2))).packed() is None
    assert _message(rng, 1, 3, wrench_cov_grasp=np.ones(36)).packed() is None
