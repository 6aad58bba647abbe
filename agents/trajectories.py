"""Reference trajectories of the cargo (position, attitude) and of the arms' pan joints.

All are analytic: position, velocity and acceleration; attitude as a rotation with angular
velocity and acceleration (world axes); pan angle with its rate. Positions are in the module
frame (origin at the aisle centre, x along the aisle), metres and seconds throughout. Defaults
stay within Astrobee's nominal limits (sources §7.3, docs/design.md / flight modes: 0.2 m/s,
0.0175 m/s^2, 0.1745 rad/s); ``fast=True`` runs the figure-eight sqrt(2) times faster
(accelerations x2, within the "difficult" mode's 0.02 m/s^2) for the "faster option".

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

Equations (t in s; every motion starts at rest through the smoothstep s(t) of ``ramp_s``):
- figure-eight, time-warped phase th(t) = omega int_0^t s: x = A sin(th), y = B sin(2 th), so
  x' = A th' cos(th), x'' = A (th'' cos(th) - th'^2 sin(th)) (and likewise for y with k = 2);
- attitude R = Rz(yaw) Rx(roll) Ry(pitch) (body-fixed roll then pitch after the yaw), each factor
  ``exp_so3`` of an axis times its angle; world angular velocity
  w = yaw' e_z + roll' e_x + pitch' e_y with e_x = Rz[:, 0], e_y = (Rz Rx)[:, 1], and
  w' = yaw'' e_z + roll'' e_x + roll' (yaw' e_z) x e_x + pitch'' e_y
       + pitch' (yaw' e_z + roll' e_x) x e_y.

Pan ramp and the closed chain: the cargo-rooted tree has no closed kinematic loop (each robot's
arm connects its own base to the cargo), so every robot can pan at once; a pan moves that robot's
base around the cargo, which its controller must follow. All robots use the same pan ramp.

The whole evaluation is compiled with numba (``@njit(cache=True)``): one call per time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from astrocargo.estimator.geometry import cross3_into, exp_so3_into, matmul3_into

NOMINAL_SPEED_MPS = 0.2
NOMINAL_ACCEL_MPS2 = 0.0175
NOMINAL_RATE_RADPS = 0.1745
# The faster option: the figure-eight at sqrt(2) times the speed, accelerations x2, within the
# "difficult" flight mode's 0.4 m/s and 0.02 m/s^2 (sources §7.3, docs/design.md, pyastrobee).
FAST_FACTOR = 2**0.5
FAST_ACCEL_MPS2 = 0.02
# Yaw ramp: final rate (rad/s), and the sudden turn (start s, smooth edge s) doubling it for 10 s.
YAW_RATE_RADPS = 0.05
YAW_TURN_S = ((40.0, 1.0), (50.0, -1.0))
YAW_TURN_EDGE_S = 5.0
# Pan ramp: a triangle wave of +-PAN_AMPLITUDE_RAD at PAN_RATE_RADPS.
PAN_AMPLITUDE_RAD = 0.4
PAN_RATE_RADPS = 0.02


@dataclass(frozen=True)
class Reference:
    """Reference at one time: cargo pose and rates (world axes) and pan angle.

    pos (m), vel (m/s), acc (m/s^2) of the cargo frame's origin; rot (3, 3) the cargo frame in
    world; w (rad/s) and wd (rad/s^2) its angular velocity and acceleration in world axes; pan
    (rad) and pan_rate (rad/s) of the arms' pan ramp.
    """

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    rot: np.ndarray
    w: np.ndarray
    wd: np.ndarray
    pan: float
    pan_rate: float


# A trajectory's constants, as the compiled evaluation takes them: one record (a record array
# of one crosses into numba as one argument).
SHAPE_DTYPE = np.dtype(
    [
        ("moving", "?"),  # figure-eight and yaw ramp (False: hover)
        ("tumble", "?"),  # roll, pitch and yaw oscillations
        ("pan_ramp", "?"),
        ("center_m", "f8", 3),
        ("figure8_amp_m", "f8", 2),  # A, B
        ("figure8_harmonic", "f8", 2),  # 1, 2
        ("omega_radps", "f8"),
        ("ramp_s", "f8"),
        ("tumble_amp_rad", "f8", 3),  # roll, pitch, yaw oscillation amplitudes
        ("tumble_omega_radps", "f8", 3),
    ],
    align=True,
)


@njit(cache=True)
def _smoothstep(t: float, t0: float, duration: float) -> tuple[float, float, float]:
    """s(t) rising smoothly 0 -> 1 over [t0, t0 + duration] (quintic 10x^3 - 15x^4 + 6x^5,
    x = (t - t0) / duration): value, rate, second derivative."""
    x = (t - t0) / duration
    if x <= 0:
        return 0.0, 0.0, 0.0
    if x >= 1:
        return 1.0, 0.0, 0.0
    s = x * x * x * (10 - 15 * x + 6 * x * x)
    ds = 30 * x * x * (1 - x) ** 2 / duration
    dds = 60 * x * (1 - x) * (1 - 2 * x) / duration**2
    return s, ds, dds


@njit(cache=True)
def _ramp_integral(t: float, t0: float, duration: float) -> float:
    """Integral over [t0, t] of the smoothstep rising over [t0, t0 + duration]."""
    x = min(max((t - t0) / duration, 0.0), 1.0)
    return duration * (x**4 * (2.5 - 3 * x + x * x)) + max(t - t0 - duration, 0.0)


@njit(cache=True)
def _oscillation(
    t: float, ramp: tuple[float, float, float], amp: float, omega: float
) -> tuple[float, float, float]:
    """amp sin(omega t) faded in by the smoothstep ``ramp`` (its value, rate and second
    derivative at t): the product's value, rate and second derivative."""
    s, ds, dds = ramp
    sn, cs = np.sin(omega * t), np.cos(omega * t)
    return (
        s * amp * sn,
        ds * amp * sn + s * amp * omega * cs,
        dds * amp * sn + 2 * ds * amp * omega * cs - s * amp * omega * omega * sn,
    )


@njit(cache=True)
def _figure_eight_into(vecs: np.ndarray, t: float, ramp: tuple[float, float, float],
                       shape: np.record) -> None:  # fmt: skip
    """Position (m), velocity and acceleration of the time-warped figure-eight about the centre,
    written into the rows 0, 1, 2 of ``vecs``: p_k = A_k sin(k th) for k = 1 (x), 2 (y),
    th = omega int s (the phase rate rises smoothly from 0 to omega, so the motion starts at
    rest without a burst of acceleration)."""
    s, ds, _ = ramp
    omega, amp, k = shape.omega_radps, shape.figure8_amp_m, shape.figure8_harmonic
    th = omega * _ramp_integral(t, 0.0, shape.ramp_s)
    thd, thdd = omega * s, omega * ds
    vecs[0], vecs[1], vecs[2] = shape.center_m, 0.0, 0.0
    for d in range(2):
        sn, cs = np.sin(k[d] * th), np.cos(k[d] * th)
        vecs[0, d] += amp[d] * sn
        vecs[1, d] = amp[d] * k[d] * thd * cs
        vecs[2, d] = amp[d] * k[d] * (thdd * cs - k[d] * thd**2 * sn)


@njit(cache=True)
def _yaw(
    t: float, ramp: tuple[float, float, float], shape: np.record
) -> tuple[float, float, float]:
    """Yaw angle (rad), rate and acceleration: a ramp to YAW_RATE_RADPS (smoothstep ``ramp``), the
    rate doubled from 40 to 50 s (edges YAW_TURN_EDGE_S), plus the tumble's yaw oscillation."""
    if not shape.moving:
        return 0.0, 0.0, 0.0
    rate = YAW_RATE_RADPS
    s, ds, _ = ramp
    yaw = rate * _ramp_integral(t, 0.0, shape.ramp_s)
    yaw_rate, yaw_acc = rate * s, rate * ds
    for t0, sign in YAW_TURN_S:
        s2, ds2, _ = _smoothstep(t, t0, YAW_TURN_EDGE_S)
        yaw += sign * rate * _ramp_integral(t, t0, YAW_TURN_EDGE_S)
        yaw_rate += sign * rate * s2
        yaw_acc += sign * rate * ds2
    if shape.tumble and shape.tumble_amp_rad[2] > 0:
        osc, osc_rate, osc_acc = _oscillation(
            t, ramp, shape.tumble_amp_rad[2], shape.tumble_omega_radps[2]
        )
        yaw += osc
        yaw_rate += osc_rate
        yaw_acc += osc_acc
    return yaw, yaw_rate, yaw_acc


@njit(cache=True)
def _attitude_zxy_into(
    rot: np.ndarray,
    w: np.ndarray,
    wd: np.ndarray,
    yaw: tuple[float, float, float],
    roll: tuple[float, float, float],
    pitch: tuple[float, float, float],
) -> None:
    """R = Rz(yaw) Rx(roll) Ry(pitch) and its angular velocity and acceleration in world axes,
    written into ``rot``, ``w`` and ``wd``, from each angle's (value rad, rate rad/s,
    acceleration rad/s^2): w = yaw' e_z + roll' e_x + pitch' e_y with e_x = Rz[:, 0],
    e_y = (Rz Rx)[:, 1]; de_x/dt = (yaw' e_z) x e_x and de_y/dt = (yaw' e_z + roll' e_x) x e_y
    give w'."""
    work_rot, work_vec = np.empty((3, 3, 3)), np.zeros((8, 3))
    rot_z, rot_zx, factor = work_rot[0], work_rot[1], work_rot[2]
    e_z, rotvec, e_x, e_y = work_vec[0], work_vec[1], work_vec[2], work_vec[3]
    w_z, w_zx, turn_x, turn_y = work_vec[4], work_vec[5], work_vec[6], work_vec[7]
    e_z[2] = 1.0
    for d in range(3):
        rotvec[d] = yaw[0] * e_z[d]
    exp_so3_into(rot_z, rotvec)
    rotvec[0], rotvec[1], rotvec[2] = roll[0], 0.0, 0.0
    exp_so3_into(factor, rotvec)
    matmul3_into(rot_zx, rot_z, factor)
    rotvec[0], rotvec[1], rotvec[2] = 0.0, pitch[0], 0.0
    exp_so3_into(factor, rotvec)
    matmul3_into(rot, rot_zx, factor)
    for d in range(3):
        e_x[d], e_y[d] = rot_z[d, 0], rot_zx[d, 1]
        w_z[d] = yaw[1] * e_z[d]
        w_zx[d] = w_z[d] + roll[1] * e_x[d]
        w[d] = w_zx[d] + pitch[1] * e_y[d]
    cross3_into(turn_x, w_z, e_x)
    cross3_into(turn_y, w_zx, e_y)
    for d in range(3):
        wd[d] = (
            yaw[2] * e_z[d]
            + roll[2] * e_x[d]
            + roll[1] * turn_x[d]
            + pitch[2] * e_y[d]
            + pitch[1] * turn_y[d]
        )


@njit(cache=True)
def _pan(t: float, ramp: tuple[float, float, float], shape: np.record) -> tuple[float, float]:
    """Pan angle (rad) and rate: a triangle wave of +-PAN_AMPLITUDE_RAD at PAN_RATE_RADPS,
    faded in by the start's smoothstep ``ramp`` (zero without a pan ramp)."""
    if not shape.pan_ramp:
        return 0.0, 0.0
    rate, amp = PAN_RATE_RADPS, PAN_AMPLITUDE_RAD
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


@njit(cache=True)
def evaluate_into(rot: np.ndarray, vecs: np.ndarray, pan: np.ndarray, t: float,
                   shapes: np.ndarray) -> None:  # fmt: skip
    """The reference at t written into ``rot`` (3, 3); ``vecs`` (5, 3), whose rows are pos,
    vel, acc, w, wd; ``pan`` (2,): pan angle and rate. ``shapes``: (1,) of ``SHAPE_DTYPE``."""
    shape = shapes[0]
    ramp = _smoothstep(t, 0.0, shape.ramp_s)
    if shape.moving:
        _figure_eight_into(vecs, t, ramp, shape)
    else:
        vecs[0], vecs[1], vecs[2] = shape.center_m, 0.0, 0.0
    roll = pitch = (0.0, 0.0, 0.0)
    if shape.tumble:
        amp, omega = shape.tumble_amp_rad, shape.tumble_omega_radps
        roll = _oscillation(t, ramp, amp[0], omega[0])
        pitch = _oscillation(t, ramp, amp[1], omega[1])
    _attitude_zxy_into(rot, vecs[3], vecs[4], _yaw(t, ramp, shape), roll, pitch)
    pan[0], pan[1] = _pan(t, ramp, shape)


class Trajectory:
    """A named reference: ``Trajectory(name, fast=False)(t)`` -> ``Reference`` at t (s);
    ``arrays(t)`` (or ``arrays_into``) packs the same numbers for the env's per-step kernels."""

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
        if self.center.shape != (3,) or not np.all(np.isfinite(self.center)):
            raise ValueError(f"center_m must be 3 finite numbers (m), got {center_m!r}")
        self.pan_ramp = bool(pan_ramp) and name != "hover"
        # Figure-eight x = A sin(wt), y = B sin(2wt): peak accelerations A w^2 and 4 B w^2.
        self.amp = np.array([0.7, 0.15])
        self.omega = 0.11 * (FAST_FACTOR if self.fast else 1.0)
        self.ramp_s = 15.0  # smooth start of every motion
        amp_deg, period_s = np.array([*self.TUMBLE, self.TUMBLE_YAW]).T
        # The shape as one record (``evaluate_into``; the env's step evaluates it compiled).
        self.shape_record = np.zeros(1, dtype=SHAPE_DTYPE)
        shape = self.shape_record[0]
        shape["moving"], shape["tumble"] = name != "hover", name == "figure8_tumble"
        shape["pan_ramp"], shape["center_m"] = self.pan_ramp, self.center
        shape["figure8_amp_m"], shape["figure8_harmonic"] = self.amp, (1.0, 2.0)
        shape["omega_radps"], shape["ramp_s"] = self.omega, self.ramp_s
        shape["tumble_amp_rad"] = np.deg2rad(amp_deg)
        shape["tumble_omega_radps"] = 2 * np.pi / period_s

    def __call__(self, t: float) -> Reference:
        rot, vecs, pan = self.arrays(t)
        return Reference(
            vecs[0], vecs[1], vecs[2], rot, vecs[3], vecs[4], float(pan[0]), float(pan[1])
        )

    def arrays(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference at ``t`` as arrays (the same numbers as ``self(t)``): rotation (3, 3);
        pos, vel, acc, w, wd as the rows of a (5, 3), world axes; (pan, pan_rate) (2,)."""
        rot, vecs, pan = np.empty((3, 3)), np.empty((5, 3)), np.empty(2)
        self.arrays_into(t, rot, vecs, pan)
        return rot, vecs, pan

    def arrays_into(self, t: float, rot: np.ndarray, vecs: np.ndarray, pan: np.ndarray) -> None:
        """``arrays(t)`` written into ``rot`` (3, 3), ``vecs`` (5, 3) and ``pan`` (2,), float64
        and C-contiguous (the env's per-step call: nothing is allocated)."""
        evaluate_into(rot, vecs, pan, float(t), self.shape_record)
