"""Reference trajectories of the cargo (position, attitude) and of the arms' pan joints.

All are analytic: position, velocity and acceleration; attitude as a rotation with angular
velocity and acceleration (world axes); pan angle with its rate. Positions are in the module
frame (origin at the aisle centre, x along the aisle). Defaults stay within Astrobee's nominal
limits (facts file section 7.3 / flight modes: 0.2 m/s, 0.0175 m/s^2, 0.1745 rad/s); ``fast=True``
runs the figure-eight sqrt(2) times faster (accelerations x2, within the "difficult" mode's
0.02 m/s^2) for the "faster option".

Named trajectories:
- ``figure8_yaw``: the seed paper's scenario. Figure-eight in the horizontal plane, a yaw ramp
  (0.05 rad/s after a smooth start) with a sudden turn at 40 s (the yaw rate doubles for 10 s, as
  the paper's "robot turns suddenly in yaw (40 s)"), and a pan ramp of the arms.
- ``figure8_tumble``: the same plus roll and pitch oscillations and a yaw oscillation on top of
  the ramp. Rotation about one axis only leaves two principal moments and one product of inertia
  unobservable; these oscillations excite all three axes with angular accelerations of the same
  order: roll (about x, expensive with robots at +-y) +-10 deg at a 12 s period, pitch (about y,
  through the robots, cheap) +-14 deg at 16 s, yaw +-10 deg at 20 s. Distinct periods, so the three
  never add up to a rotation about one fixed axis (roll and pitch at one period would); peak rates
  0.09, 0.10 and 0.05 + 0.05 rad/s. Measured with two robots and nominal noise: about 5 % of the
  control steps saturate some propulsion axis and the cargo tracks within 1 cm; the previous
  +-10 deg / 24 s roll left the smallest principal moment's Cramer-Rao bound at 21 %.
- ``hover``: hold the start pose (controller tests).

Pan ramp and the closed chain: the cargo-rooted tree has no closed kinematic loop (each robot's
arm connects its own base to the cargo), so every robot can pan at once; a pan moves that robot's
base around the cargo, which its controller must follow. All robots use the same pan ramp.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from astrocargo.estimator.rne import v_add, v_cross, v_scale

NOMINAL_SPEED_MPS = 0.2
NOMINAL_ACCEL_MPS2 = 0.0175
NOMINAL_RATE_RADPS = 0.1745
# The faster option: the figure-eight at sqrt(2) times the speed, accelerations x2, within the
# "difficult" flight mode's 0.4 m/s and 0.02 m/s^2 (facts file section 7.3, pyastrobee).
FAST_FACTOR = 2**0.5
FAST_ACCEL_MPS2 = 0.02


@dataclass(frozen=True)
class Reference:
    """Reference at one time: cargo pose and rates (world axes) and pan angle."""

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    rot: np.ndarray  # (3, 3) cargo frame in world
    w: np.ndarray  # angular velocity, world axes
    wd: np.ndarray  # angular acceleration, world axes
    pan: float
    pan_rate: float


class ReferenceValues(NamedTuple):
    """A ``Reference`` on Python floats: vectors as 3 floats, the rotation as its rows (for
    code on the float helpers of ``estimator.rne``; one evaluation per control step)."""

    pos: Sequence[float]
    vel: Sequence[float]
    acc: Sequence[float]
    rot: Sequence[Sequence[float]]
    w: Sequence[float]
    wd: Sequence[float]
    pan: float
    pan_rate: float

    def to_reference(self) -> Reference:
        return Reference(
            np.array(self.pos),
            np.array(self.vel),
            np.array(self.acc),
            np.array(self.rot),
            np.array(self.w),
            np.array(self.wd),
            self.pan,
            self.pan_rate,
        )


def _rot(axis: int, angle: float) -> list[list[float]]:
    """Rows of the rotation by ``angle`` about axis ``axis`` (0, 1, 2: x, y, z)."""
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    r[i][i] = r[j][j] = c
    r[i][j], r[j][i] = -s, s
    return r


def _smoothstep(t: float, t0: float, duration: float) -> tuple[float, float, float]:
    """s(t) rising smoothly 0 -> 1 over [t0, t0 + duration]: value, rate, second derivative."""
    x = (t - t0) / duration
    if x <= 0:
        return 0.0, 0.0, 0.0
    if x >= 1:
        return 1.0, 0.0, 0.0
    s = x * x * x * (10 - 15 * x + 6 * x * x)
    ds = 30 * x * x * (1 - x) ** 2 / duration
    dds = 60 * x * (1 - x) * (1 - 2 * x) / duration**2
    return s, ds, dds


def _oscillation(
    t: float, ramp: tuple[float, float, float], amp: float, omega: float
) -> tuple[float, float, float]:
    """amp sin(omega t) faded in by the smoothstep ``ramp`` (its value, rate and second
    derivative at t): the product's value, rate and second derivative."""
    s, ds, dds = ramp
    sn, cs = math.sin(omega * t), math.cos(omega * t)
    return (
        s * amp * sn,
        ds * amp * sn + s * amp * omega * cs,
        dds * amp * sn + 2 * ds * amp * omega * cs - s * amp * omega * omega * sn,
    )


def _combine(*terms: tuple[float, tuple[float, float, float]]) -> tuple[float, float, float]:
    """sum_k c_k v_k of 3-vectors given as (c_k, v_k), added left to right (as numpy would)."""
    (c, v), *rest = terms
    out = v_scale(c, v)
    for c, v in rest:
        out = v_add(out, v_scale(c, v))
    return out


class Trajectory:
    """A named reference. ``Trajectory(name, fast=False)(t)`` -> ``Reference``;
    ``values(t)``: the same on Python floats (what the env evaluates once per control step).
    """

    NAMES = ("figure8_yaw", "figure8_tumble", "hover")
    # figure8_tumble's (amplitude deg, period s) of roll (about x) then pitch (about y), and of
    # a yaw oscillation added to the yaw ramp.
    TUMBLE = ((10.0, 12.0), (14.0, 16.0))
    TUMBLE_YAW = (10.0, 20.0)

    def __init__(
        self,
        name: str = "figure8_yaw",
        fast: bool = False,
        center_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        pan_ramp: bool = True,
    ) -> None:
        if name not in self.NAMES:
            raise ValueError(f"unknown trajectory {name!r}; allowed: {list(self.NAMES)}")
        self.name = name
        self.fast = bool(fast)
        self.center = np.asarray(center_m, dtype=float)
        self.pan_ramp = bool(pan_ramp) and name != "hover"
        # Figure-eight x = A sin(wt), y = B sin(2wt): peak accelerations A w^2 and 4 B w^2.
        self.amp = np.array([0.7, 0.15])
        self.omega = 0.11 * (FAST_FACTOR if self.fast else 1.0)
        self._figure8 = ((float(self.amp[0]), 1.0), (float(self.amp[1]), 2.0))  # (A, 1), (B, 2)
        self.ramp_s = 15.0  # smooth start of every motion
        # (amplitude rad, angular frequency rad/s) of the oscillations (TUMBLE, TUMBLE_YAW).
        self._tumble = [
            (float(np.deg2rad(amp_deg)), 2 * np.pi / period) for amp_deg, period in self.TUMBLE
        ]
        self._tumble_yaw = (float(np.deg2rad(self.TUMBLE_YAW[0])), 2 * np.pi / self.TUMBLE_YAW[1])

    def __call__(self, t: float) -> Reference:
        return self.values(t).to_reference()

    def values(self, t: float) -> ReferenceValues:
        """The reference at ``t`` on Python floats (the same numbers as ``self(t)``)."""
        ramp = _smoothstep(t, 0.0, self.ramp_s)
        s, ds, _ = ramp
        pos, vel, acc = self.center.tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        if self.name != "hover":
            # Time warp: the figure-eight's phase rate rises smoothly from 0 to omega, so the
            # motion starts at rest without a burst of acceleration.
            w = self.omega
            th, thd, thdd = w * self._ramp_integral(t, 0.0, self.ramp_s), w * s, w * ds
            for axis, (amp, k) in enumerate(self._figure8):
                sn, cs = math.sin(k * th), math.cos(k * th)
                pos[axis] += amp * sn
                vel[axis] = amp * k * thd * cs
                acc[axis] = amp * k * (thdd * cs - k * thd**2 * sn)
        yaw, yaw_rate, yaw_acc = self._yaw(t, ramp)
        rot = _rot(2, yaw)
        w_world = (0.0, 0.0, yaw_rate)
        wd_world = (0.0, 0.0, yaw_acc)
        if self.name == "figure8_tumble":
            # Body-fixed roll (x) then pitch (y) oscillations after the yaw: R = Rz Rx Ry.
            (roll, roll_d, roll_dd), (pitch, pitch_d, pitch_dd) = (
                _oscillation(t, ramp, a, om) for a, om in self._tumble
            )
            rot_zx = np.array(rot) @ np.array(_rot(0, roll))
            rot = (rot_zx @ np.array(_rot(1, pitch))).tolist()
            # Angular velocity and acceleration in world axes of R = Rz(yaw) Rx(roll) Ry(pitch).
            ez = (0.0, 0.0, 1.0)
            ex = (math.cos(yaw), math.sin(yaw), 0.0)
            ey = tuple(rot_zx[:, 1].tolist())
            w_world = _combine((yaw_rate, ez), (roll_d, ex), (pitch_d, ey))
            # d/dt ex = w_z x ex; d/dt ey = (yaw_rate ez + roll_d ex) x ey.
            dex = v_cross(v_scale(yaw_rate, ez), ex)
            dey = v_cross(_combine((yaw_rate, ez), (roll_d, ex)), ey)
            wd_world = _combine(
                (yaw_acc, ez), (roll_dd, ex), (roll_d, dex), (pitch_dd, ey), (pitch_d, dey)
            )
        pan, pan_rate = self._pan(t, ramp)
        return ReferenceValues(pos, vel, acc, rot, w_world, wd_world, pan, pan_rate)

    @staticmethod
    def _ramp_integral(t: float, t0: float, duration: float) -> float:
        """Integral over [t0, t] of the smoothstep rising over [t0, t0 + duration]."""
        x = min(max((t - t0) / duration, 0.0), 1.0)
        return duration * (x**4 * (2.5 - 3 * x + x * x)) + max(t - t0 - duration, 0.0)

    def _yaw(self, t: float, ramp: tuple[float, float, float]) -> tuple[float, float, float]:
        """Yaw angle, rate and acceleration; ``ramp`` is the smoothstep of the start at t."""
        if self.name == "hover":
            return 0.0, 0.0, 0.0
        rate = 0.05
        # Base ramp: yaw rate rises smoothly to `rate` over the first ramp_s seconds.
        s, ds, _ = ramp
        yaw = rate * self._ramp_integral(t, 0.0, self.ramp_s)
        yaw_rate, yaw_acc = rate * s, rate * ds
        # Sudden turn at 40 s: the rate doubles for 10 s (smooth 5 s edges).
        for t0, sign in ((40.0, 1.0), (50.0, -1.0)):
            s2, ds2, _ = _smoothstep(t, t0, 5.0)
            yaw += sign * rate * self._ramp_integral(t, t0, 5.0)
            yaw_rate += sign * rate * s2
            yaw_acc += sign * rate * ds2
        if self.name == "figure8_tumble" and self.TUMBLE_YAW[0] > 0:
            osc, osc_rate, osc_acc = _oscillation(t, ramp, *self._tumble_yaw)
            yaw += osc
            yaw_rate += osc_rate
            yaw_acc += osc_acc
        return yaw, yaw_rate, yaw_acc

    def _pan(self, t: float, ramp: tuple[float, float, float]) -> tuple[float, float]:
        """Pan ramp: a triangle wave of +-0.4 rad at 0.02 rad/s, smoothed at the start
        (``ramp``: the smoothstep of the start at t)."""
        if not self.pan_ramp:
            return 0.0, 0.0
        rate, amp = 0.02, 0.4
        period = 4 * amp / rate
        phase = t % period
        if phase < amp / rate:
            pan, d = rate * phase, rate
        elif phase < 3 * amp / rate:
            pan, d = amp - rate * (phase - amp / rate), -rate
        else:
            pan, d = -amp + rate * (phase - 3 * amp / rate), rate
        s, ds, _ = ramp
        return s * pan, ds * pan + s * d
