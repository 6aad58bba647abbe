"""Communication channel: latency rounding, loss and noise statistics, copies, determinism,
validation."""

from dataclasses import dataclass, replace

import numpy as np
import pytest

from astrocargo.envs.comms import CommChannel, freeze_arrays
from astrocargo.estimator.cargo_estimator import WrenchMessage

DT_S = 0.016


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _message(sender: int, stamp: int, rot: np.ndarray | None = None) -> WrenchMessage:
    rot = np.eye(3) if rot is None else rot
    wrench_grasp = np.array([0.1, -0.2, 0.3, 0.01, -0.02, 0.03])
    return WrenchMessage(
        sender=sender,
        stamp=stamp,
        wrench_grasp=wrench_grasp,
        wrench_world=np.concatenate((rot @ wrench_grasp[:3], rot @ wrench_grasp[3:])),
        grasp_pos_world=np.array([0.0, 0.2, 0.0]),
        grasp_rot_world=rot,
        fix=False,
        wrench_cov_grasp=np.eye(6) * 1e-6,
    )


def _channel(n=2, latency_s=0.0, drop_prob=0.0, noise_std=(0.0, 0.0), seed=0) -> CommChannel:
    return CommChannel(n, latency_s, drop_prob, noise_std, DT_S, np.random.default_rng(seed))


@pytest.mark.parametrize(
    ("latency_s", "steps"),
    [(0.0, 0), (0.007, 0), (0.008, 1), (0.016, 1), (0.02, 1), (0.025, 2), (0.2, 13), (1.0, 63)],
)
def test_latency_is_rounded_to_whole_periods(latency_s, steps):
    """Latency is the nearest whole number of control periods (halves up), and a message sent
    at step k arrives at step k + that number, not earlier."""
    ch = _channel(latency_s=latency_s)
    assert ch.latency_steps == steps
    ch.send(_message(0, 5), 5)
    for k in range(5, 5 + steps):
        assert ch.deliver(k) == {0: [], 1: []}
        assert ch.stats["in_flight"] == 1
    out = ch.deliver(5 + steps)
    assert len(out[1]) == 1 and out[0] == []
    assert out[1][0].stamp == 5
    assert ch.stats == {"sent": 1, "delivered": 1, "dropped": 0, "in_flight": 0}


def test_send_defaults_to_the_stamp_and_late_collection_gets_everything():
    ch = _channel(n=3, latency_s=0.032)
    ch.send(_message(1, 10))  # step = stamp
    ch.send(_message(2, 11), 11)
    out = ch.deliver(20)
    assert [m.stamp for m in out[0]] == [10, 11]
    assert [m.sender for m in out[1]] == [2]
    assert [m.sender for m in out[2]] == [1]
    assert ch.deliver(21) == {0: [], 1: [], 2: []}


def test_due_tells_whether_deliver_has_copies():
    ch = _channel(n=3, latency_s=0.032)  # 2 periods
    assert not ch.due(0)
    ch.send(_message(1, 10))
    assert not ch.due(11) and ch.due(12) and ch.due(30)
    ch.deliver(12)
    assert not ch.due(30)


def test_each_receiver_gets_its_own_copy():
    ch = _channel(n=3)
    msg = _message(0, 1)
    ch.send(msg, 1)
    out = ch.deliver(1)
    a, b = out[1][0], out[2][0]
    assert a is not b and a is not msg
    assert a.wrench_grasp is not b.wrench_grasp and a.wrench_grasp is not msg.wrench_grasp
    np.testing.assert_array_equal(a.wrench_grasp, msg.wrench_grasp)
    a.wrench_grasp[:] = 0.0
    np.testing.assert_array_equal(b.wrench_grasp, msg.wrench_grasp)
    assert out[0] == []  # never to the sender


def test_a_frozen_message_is_shared_and_a_shared_array_copied_once():
    """A message whose arrays are all read-only (``freeze_arrays``) reaches every receiver as
    is; a writable array that two fields share is copied once per receiver, the copy shared by
    those fields as in the original."""
    ch = _channel(n=3)
    msg = freeze_arrays(_message(0, 1))
    assert not msg.wrench_grasp.flags.writeable and not msg.grasp_rot_world.flags.writeable
    ch.send(msg, 1)
    out = ch.deliver(1)
    assert out[1][0] is msg and out[2][0] is msg
    var = np.ones(4)
    ch.send(replace(_message(0, 2), motion_var=var, motion_band=var), 2)
    out = ch.deliver(2)
    a, b = out[1][0], out[2][0]
    assert a.motion_var is a.motion_band and a.motion_var is not var
    assert a.motion_var is not b.motion_var


def test_frozen_and_writable_messages_get_the_same_losses_delays_and_noise():
    """Sharing frozen messages changes no draw: with loss, latency and noise a seeded channel
    hands out the same copies either way, each receiver its own noisy wrenches, the other
    arrays shared with the sender's read-only ones."""
    runs = []
    for frozen in (False, True):
        ch = _channel(n=3, latency_s=0.05, drop_prob=0.4, noise_std=(0.01, 0.001), seed=5)
        got = []
        for k in range(200):
            msg = _message(k % 3, k, _rot_z(0.1 * k))
            ch.send(freeze_arrays(msg) if frozen else msg, k)
            for receiver, msgs in ch.deliver(k).items():
                got += [(receiver, m.stamp, m.wrench_grasp, m.wrench_world, m) for m in msgs]
        runs.append(got)
    assert len(runs[0]) == len(runs[1]) > 100
    for (ra, sa, ga, wa, _), (rb, sb, gb, wb, mb) in zip(*runs, strict=True):
        assert (ra, sa) == (rb, sb)
        np.testing.assert_array_equal(ga, gb)
        np.testing.assert_array_equal(wa, wb)
        assert mb.wrench_grasp.flags.writeable and not mb.grasp_pos_world.flags.writeable


def test_drop_statistics():
    """Each copy is lost independently with drop_prob: the count is binomial."""
    p, n_msgs, n_robots = 0.3, 4000, 3
    ch = _channel(n=n_robots, drop_prob=p)
    delivered = 0
    for k in range(n_msgs):
        ch.send(_message(k % n_robots, k), k)
        delivered += sum(len(v) for v in ch.deliver(k).values())
    copies = n_msgs * (n_robots - 1)
    dropped = ch.stats["dropped"]
    assert dropped + delivered == copies
    assert ch.stats == {"sent": n_msgs, "delivered": delivered, "dropped": dropped, "in_flight": 0}
    sigma = np.sqrt(copies * p * (1 - p))
    assert abs(dropped - copies * p) < 4 * sigma
    all_lost = _channel(drop_prob=1.0)
    all_lost.send(_message(0, 0), 0)
    assert all_lost.deliver(0) == {0: [], 1: []}
    assert all_lost.stats["dropped"] == 1


def test_noise_statistics_and_frame_consistency():
    """Noise has the stated std per axis (force, moment) and zero mean; the world-axes wrench
    receives the same perturbation rotated with the sender's grasp attitude."""
    std = (0.02, 0.003)
    rot = _rot_z(0.7)
    ch = _channel(noise_std=std)
    msg = _message(0, 0, rot)
    errs_g, errs_w = [], []
    for k in range(4000):
        ch.send(replace(msg, stamp=k), k)
        (copy,) = ch.deliver(k)[1]
        errs_g.append(copy.wrench_grasp - msg.wrench_grasp)
        errs_w.append(copy.wrench_world - msg.wrench_world)
    errs_g, errs_w = np.array(errs_g), np.array(errs_w)
    expected = np.repeat(std, 3)
    np.testing.assert_allclose(errs_g.std(axis=0), expected, rtol=0.06)
    assert np.all(np.abs(errs_g.mean(axis=0)) < 4 * expected / np.sqrt(len(errs_g)))
    np.testing.assert_allclose(errs_w[:, :3], errs_g[:, :3] @ rot.T, atol=1e-15)
    np.testing.assert_allclose(errs_w[:, 3:], errs_g[:, 3:] @ rot.T, atol=1e-15)
    # Fields other than the wrenches are untouched.
    np.testing.assert_array_equal(copy.grasp_pos_world, msg.grasp_pos_world)
    np.testing.assert_array_equal(copy.wrench_cov_grasp, msg.wrench_cov_grasp)


def _run(seed: int) -> list[tuple[int, int, np.ndarray]]:
    ch = _channel(n=3, latency_s=0.05, drop_prob=0.4, noise_std=(0.01, 0.001), seed=seed)
    out = []
    for k in range(200):
        ch.send(_message(k % 3, k), k)
        for receiver, msgs in ch.deliver(k).items():
            out += [(receiver, m.stamp, m.wrench_grasp) for m in msgs]
    return out


def test_deterministic_given_the_generator():
    a, b, c = _run(1), _run(1), _run(2)
    assert len(a) == len(b)
    for (ra, sa, wa), (rb, sb, wb) in zip(a, b, strict=True):
        assert (ra, sa) == (rb, sb)
        np.testing.assert_array_equal(wa, wb)
    assert [(r, s) for r, s, _ in a] != [(r, s) for r, s, _ in c]


@dataclass(frozen=True)
class _Plain:
    sender: int
    stamp: int


def test_any_dataclass_with_a_sender_passes_without_noise():
    ch = _channel()
    ch.send(_Plain(1, 3))
    assert ch.deliver(3)[0] == [_Plain(1, 3)]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_robots": 0}, "n_robots"),
        ({"n_robots": 1.5}, "n_robots"),
        ({"n_robots": True}, "n_robots"),
        ({"latency_s": -0.1}, "latency_s"),
        ({"latency_s": float("nan")}, "latency_s"),
        ({"drop_prob": 1.5}, "drop_prob"),
        ({"drop_prob": -0.1}, "drop_prob"),
        ({"noise_std": (0.1,)}, "noise_std"),
        ({"noise_std": (0.1, -1.0)}, "noise_std"),
        ({"noise_std": (0.1, float("inf"))}, "noise_std"),
        ({"dt_s": 0.0}, "dt_s"),
        ({"rng": 3}, "rng"),
    ],
)
def test_validation(kwargs, match):
    args = {
        "n_robots": 2,
        "latency_s": 0.0,
        "drop_prob": 0.0,
        "noise_std": (0.0, 0.0),
        "dt_s": DT_S,
        "rng": np.random.default_rng(0),
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        CommChannel(**args)


def test_send_validation():
    ch = _channel()
    with pytest.raises(ValueError, match="sender"):
        ch.send(_message(2, 0), 0)
    with pytest.raises(ValueError, match="dataclass"):
        ch.send({"sender": 0}, 0)
    with pytest.raises(ValueError, match="step"):
        ch.send(_message(0, 0), 1.5)
