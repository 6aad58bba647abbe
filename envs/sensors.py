"""What each robot senses, and the seeded noise on it.

Readings come from the MJCF sensors of each robot (``base_pos`` / ``base_quat`` of the base body,
``tilt_pos`` / ``pan_pos`` encoders) and the IMU site's motion, and must be read after
``mj_forward`` (or its position and velocity stages) so they describe the current state
(pitfalls: after ``mj_step`` they lag one step).
The MJCF ``noise`` attribute does nothing at run time, so noise is added here from the env's
``np.random.Generator``. Nothing of the cargo is sensed.

IMU readings are averages over the control period (``begin_period`` marks its start): the change of
the IMU point's velocity over the period divided by its length, and the rotation over the period
as a mean rate. The Epson G362P averages internally (64-tap moving average at 125 samples/s, facts
file section 4.1), and a point sample would alias the arm servos' intra-period acceleration pattern
(it repeats at exactly the 62.5 Hz sample rate) into a bias that no low-pass filter removes.

Frames: accelerometer (specific force = acceleration in microgravity, m/s^2) and gyro (rad/s) in
the IMU frame; localization pose of the base frame in the module (world) frame, quaternion
(w, x, y, z); joint angles in rad.

Noise profiles (white, per 62.5 Hz sample, after the IMU's internal filtering). ``nominal`` uses
the floors of docs/design.md ("Noise model and its sources"): accelerometer 1e-3 m/s^2 and gyro
2e-4 rad/s (Epson G362-class MEMS IMU; the Astrobee IMU is an Epson G362P, sources §4,
docs/design.md), localization 5 mm and 0.2 deg at 62.5 / 20 = 3.125 Hz (the simulator's
sparse-map features arrive at 3 Hz, sources §4), encoders 1e-3 rad, actuation 0.005 N + 2 % of
the command and 5e-4 N m + 2 %.
``ideal``: no noise at all; ``actuation_only``: perfect sensors with ``nominal``'s actuation noise.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, replace
from typing import NamedTuple

import mujoco
import numpy as np
from numba import njit

from astrocargo.envs.world import World
from astrocargo.estimator.geometry import (
    cross3_into,
    exp_so3_into,
    log_so3_into,
    matmul3_into,
    matvec3_into,
    quat_mul_into,
    rotvec_to_quat_into,
)
from astrocargo.estimator.records import bound_views, interned, record_of


@dataclass(frozen=True)
class NoiseProfile:
    """Standard deviations of white noise per sample, and the localization rate divisor."""

    accel_std: float  # m/s^2, per axis
    gyro_std: float  # rad/s, per axis
    position_std_m: float  # per axis
    attitude_std_rad: float  # per axis (small rotation vector)
    encoder_std_rad: float
    force_std_n: float  # actuation: absolute part
    force_rel: float  # actuation: fraction of the command
    torque_std_nm: float
    torque_rel: float
    localization_every: int = 20  # control steps between pose fixes (62.5 / 20 = 3.125 Hz)


NOISE_PROFILES: dict[str, NoiseProfile] = {
    "ideal": NoiseProfile(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, localization_every=1),
    "nominal": NoiseProfile(
        accel_std=1e-3,
        gyro_std=2e-4,
        position_std_m=5e-3,
        attitude_std_rad=np.deg2rad(0.2),
        encoder_std_rad=1e-3,
        force_std_n=5e-3,
        force_rel=0.02,
        torque_std_nm=5e-4,
        torque_rel=0.02,
    ),
}
# Perfect sensors, nominal actuation: what the propulsion noise alone leaves to estimate (it
# bounds what any sensor fusion could reach under `nominal`; docs/estimation_limits.md).
NOISE_PROFILES["actuation_only"] = replace(
    NOISE_PROFILES["nominal"],
    accel_std=0.0,
    gyro_std=0.0,
    position_std_m=0.0,
    attitude_std_rad=0.0,
    encoder_std_rad=0.0,
)


def estimator_noise_kwargs(profile: NoiseProfile) -> dict:
    """What a robot knows of its own sensors and propulsion, as ``CargoEstimator`` settings."""
    p = profile
    return {
        "actuation_noise": (p.force_std_n, p.force_rel, p.torque_std_nm, p.torque_rel),
        "sensor_noise": (p.accel_std, p.gyro_std, p.encoder_std_rad),
        "localization_noise": (p.position_std_m, p.attitude_std_rad),
    }


def noise_profile(name: str) -> NoiseProfile:
    """The named profile; ``ValueError`` lists the allowed names."""
    if name not in NOISE_PROFILES:
        raise ValueError(
            f"unknown sensor noise profile {name!r}; allowed: {sorted(NOISE_PROFILES)}"
        )
    return NOISE_PROFILES[name]


class SensorPacket(NamedTuple):
    """One robot's readings at one control step (immutable; a named tuple, which costs a third
    of a frozen dataclass to build: the estimators take one per robot and step)."""

    time_s: float
    accel_imu: np.ndarray | None  # (3,) m/s^2, IMU frame; None: the frame is missing (a fault)
    gyro_imu: np.ndarray | None  # (3,) rad/s, IMU frame; None with accel_imu
    joint_pos_rad: np.ndarray  # (n_joints,)
    base_pos_world: np.ndarray | None  # (3,) m, only at a localization fix
    base_quat_world: np.ndarray | None  # (4,) w x y z, only at a localization fix


# The fields of ``SensorReadings.empty_record``'s record, in the order of the readings' arrays.
READINGS_FIELDS = ("accel", "gyro", "joints", "pos", "quat", "has_imu", "has_fix")


@dataclass(slots=True)
class SensorReadings:
    """Every robot's readings at one control step as arrays, one row per robot; a row's IMU
    frame and fix count only where ``has_imu`` / ``has_fix`` (the other entries are zeros or
    stale; the env clears the masks of faulted rows in place). ``packet(k)`` is row k as a
    ``SensorPacket``."""

    time_s: float
    accel_imu: np.ndarray  # (n, 3) m/s^2, IMU frame
    gyro_imu: np.ndarray  # (n, 3) rad/s, IMU frame
    joint_pos_rad: np.ndarray  # (n, n_joints)
    base_pos_world: np.ndarray  # (n, 3) m
    base_quat_world: np.ndarray  # (n, 4) w x y z
    has_imu: np.ndarray  # (n,) bool: the IMU frame arrived
    has_fix: np.ndarray  # (n,) bool: a localization fix (at every localization_every-th step)

    def packet(self, k: int) -> SensorPacket:
        """Row k, with None for a missing IMU frame or fix."""
        imu = (self.accel_imu[k], self.gyro_imu[k]) if self.has_imu[k] else (None, None)
        fix = (self.base_pos_world[k], self.base_quat_world[k]) if self.has_fix[k] else (None,) * 2
        return SensorPacket(self.time_s, *imu, self.joint_pos_rad[k], *fix)

    @classmethod
    def empty(cls, n_rows: int, n_joints: int = 2) -> SensorReadings:
        """Readings of ``n_rows`` robots, every value zero, nothing valid."""
        return cls(
            0.0, np.zeros((n_rows, 3)), np.zeros((n_rows, 3)), np.zeros((n_rows, n_joints)),
            np.zeros((n_rows, 3)), np.zeros((n_rows, 4)), np.zeros(n_rows, dtype=np.bool_),
            np.zeros(n_rows, dtype=np.bool_),
        )  # fmt: skip

    @classmethod
    def empty_record(cls, n_rows: int, n_joints: int = 2) -> tuple[SensorReadings, np.ndarray]:
        """``empty``'s readings, each array a view of one record (``estimator.records.record_of``;
        fields ``READINGS_FIELDS``), and that record: what the compiled step writes
        (``step_kernels.sense_and_navigate``)."""
        record = np.zeros(1, dtype=_readings_dtype(n_rows, n_joints))
        readings = cls(0.0, *bound_views(record).values())
        return readings, record

    def view_record(self, record: np.ndarray) -> None:
        """The arrays become views of ``record``'s fields (``empty_record``; after a copy, whose
        arrays are detached from the copied record)."""
        names = [f.name for f in dataclasses.fields(self)[1:]]
        for name, view in zip(names, bound_views(record).values(), strict=True):
            setattr(self, name, view)

    def in_rows(self, rows: list[int], n_rows: int) -> SensorReadings:
        """These readings as rows ``rows`` of ``n_rows`` (the others: zeros, nothing valid)."""
        out = []
        for value in dataclasses.astuple(self)[1:]:
            full = np.zeros((n_rows, *value.shape[1:]), dtype=value.dtype)
            full[rows] = value
            out.append(full)
        return SensorReadings(self.time_s, *out)


class FreshReadings:
    """New readings of ``n_rows`` robots and their record at each call, as
    ``SensorReadings.empty_record`` gives them, cut from blocks of ``block`` records allocated
    at once (one allocation and one set of field views per block, not per step). Readings kept
    by their user (an estimator) keep their block alive."""

    def __init__(self, n_rows: int, n_joints: int = 2, block: int = 64) -> None:
        self.dtype = _readings_dtype(n_rows, n_joints)
        self.block = block
        self._start_block()

    def _start_block(self) -> None:
        self._records = np.zeros(self.block, dtype=self.dtype)
        views = [self._records[name] for name in self.dtype.names]
        self._fields = tuple(
            v.view(np.bool_) if v.dtype == np.uint8 else v for v in views
        )  # (block, ...) each: row j is record j's field
        self._next = 0

    def __call__(self) -> tuple[SensorReadings, np.ndarray]:
        if self._next == self.block:
            self._start_block()
        j = self._next
        self._next = j + 1
        return SensorReadings(0.0, *(f[j] for f in self._fields)), self._records[j : j + 1]

    # A copy (copy.deepcopy, pickle) starts a block of its own: copied views would be detached.
    def __getstate__(self) -> dict:
        return {"dtype": self.dtype, "block": self.block}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.dtype = interned(self.dtype)  # unpickled: a new dtype object
        self._start_block()


@functools.cache
def _readings_dtype(n_rows: int, n_joints: int) -> np.dtype:
    """The dtype of ``SensorReadings.empty_record``'s record (built once per shape)."""
    empty = SensorReadings.empty(n_rows, n_joints)
    return record_of(dict(zip(READINGS_FIELDS, dataclasses.astuple(empty)[1:], strict=True))).dtype


@njit(cache=True, inline="always")
def imu_site_state_into(vel, rot, cvel, site_xpos, site_xmat, subtree_com, bodies, roots, sites):
    """Linear velocity ``vel`` (n, 3), world axes, and rotation ``rot`` (n, 3, 3) of each site,
    written in place: its body's spatial velocity (MuJoCo's ``cvel``: angular, linear at the
    root's subtree centre of mass c) moved to the site's point p, v_p = v_c - (p - c) x w (as
    ``mj_objectVelocity`` with world axes); the rotation is MuJoCo's ``site_xmat``."""
    lever_spin = np.empty((2, 3))
    lever, spin = lever_spin[0], lever_spin[1]
    for k in range(sites.shape[0]):
        w, v = cvel[bodies[k], :3], cvel[bodies[k], 3:]
        for j in range(3):
            lever[j] = site_xpos[sites[k], j] - subtree_com[roots[k], j]
        cross3_into(spin, lever, w)
        for j in range(3):
            vel[k, j] = v[j] - spin[j]
        rot[k] = site_xmat[sites[k]].reshape(3, 3)


@njit(cache=True)
def imu_site_state(cvel, site_xpos, site_xmat, subtree_com, bodies, roots, sites):
    """``imu_site_state_into`` into new arrays: velocities (n, 3) and rotations (n, 3, 3)."""
    n = sites.shape[0]
    vel, rot = np.empty((n, 3)), np.empty((n, 3, 3))
    imu_site_state_into(vel, rot, cvel, site_xpos, site_xmat, subtree_com, bodies, roots, sites)
    return vel, rot


@njit(cache=True, inline="always")
def imu_period_means_into(accel, gyro, v0, r0, v1, r1, dt_s):
    """Mean specific force ``accel`` and angular rate ``gyro`` of each IMU over a period of
    ``dt_s``, IMU frame (n, 3) each, written in place, from its velocity (world axes) and
    rotation at the period's start and end: phi = log(R0^T R1), gyro = phi / dt,
    accel = (R0 exp(phi / 2))^T (v1 - v0) / dt (the velocity change in the mid-period frame)."""
    work_rot, work_vec = np.empty((2, 3, 3)), np.empty((4, 3))
    r_rel, r_mid = work_rot[0], work_rot[1]
    rotvec, half, dv, force = work_vec[0], work_vec[1], work_vec[2], work_vec[3]
    for k in range(v0.shape[0]):
        matmul3_into(r_rel, r0[k].T, r1[k])
        log_so3_into(rotvec, r_rel)
        for j in range(3):
            half[j] = 0.5 * rotvec[j]
        exp_so3_into(r_rel, half)
        matmul3_into(r_mid, r0[k], r_rel)
        for j in range(3):
            dv[j] = v1[k, j] - v0[k, j]
        matvec3_into(force, r_mid.T, dv)
        for j in range(3):
            accel[k, j] = force[j] / dt_s
            gyro[k, j] = rotvec[j] / dt_s


@njit(cache=True)
def imu_period_means(v0, r0, v1, r1, dt_s):
    """``imu_period_means_into`` into new arrays: accel, gyro (n, 3) each."""
    n = v0.shape[0]
    accel, gyro = np.empty((n, 3)), np.empty((n, 3))
    imu_period_means_into(accel, gyro, v0, r0, v1, r1, dt_s)
    return accel, gyro


@njit(cache=True)
def noisy_readings(v0, r0, dt_s, cvel, site_xpos, site_xmat, subtree_com, bodies, roots, sites,
                   sensordata, joint_adr, pos_adr, quat_adr, noise, fix):  # fmt: skip
    """Every robot's readings at the end of a period of ``dt_s`` that started with the IMU
    velocities ``v0`` and rotations ``r0``: the IMU means (``imu_site_state`` now, then
    ``imu_period_means``) and the MJCF sensors (``sensordata`` at the addresses, (n, k) each),
    plus the drawn ``noise`` (n, draws) in ``_NOISE_DRAWS`` then ``_FIX_DRAWS`` order; at a fix
    the pose too, the attitude perturbed in the body frame: q exp(noise). Returns accel, gyro,
    joints, pos, quat (zeros without a fix)."""
    v1, r1 = imu_site_state(cvel, site_xpos, site_xmat, subtree_com, bodies, roots, sites)
    n = v0.shape[0]
    accel, gyro, joints = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, joint_adr.shape[1]))
    pos, quat = np.zeros((n, 3)), np.zeros((n, 4))
    _readings_into(
        v0, r0, v1, r1, dt_s, sensordata, joint_adr, pos_adr, quat_adr, noise, fix,
        np.arange(n), accel, gyro, joints, pos, quat,
    )  # fmt: skip
    return accel, gyro, joints, pos, quat


@njit(cache=True, inline="always")
def _readings_into(v0, r0, v1, r1, dt_s, sensordata, joint_adr, pos_adr, quat_adr, noise, fix,
                   rows, accel, gyro, joints, pos, quat):  # fmt: skip
    """``noisy_readings``' values from the IMU states at the period's start and end, robot k's
    written into row ``rows[k]`` of ``accel``, ``gyro``, ``joints`` and, at a ``fix``, ``pos``
    and ``quat`` (left as they are without one)."""
    accel_mean, gyro_mean = imu_period_means(v0, r0, v1, r1, dt_s)
    quats = np.empty((2, 4))  # the measured quaternion and the noise's
    measured, perturbation = quats[0], quats[1]
    for k in range(rows.shape[0]):
        i = rows[k]
        for j in range(3):
            accel[i, j] = accel_mean[k, j] + noise[k, j]
            gyro[i, j] = gyro_mean[k, j] + noise[k, 3 + j]
        for j in range(joint_adr.shape[1]):
            joints[i, j] = sensordata[joint_adr[k, j]] + noise[k, 6 + j]
        if fix:
            for j in range(3):
                pos[i, j] = sensordata[pos_adr[k, j]] + noise[k, 8 + j]
            for j in range(4):
                measured[j] = sensordata[quat_adr[k, j]]
            rotvec_to_quat_into(perturbation, noise[k, 11:14])
            quat_mul_into(quat[i], measured, perturbation)


@njit(cache=True)
def imu_state_into(v0, r0, cvel, site_xpos, site_xmat, subtree_com, imu_index):
    """``imu_site_state`` of the IMUs ``imu_index`` (3, H: bodies, roots, sites) written into
    ``v0`` (H, 3) and ``r0`` (H, 3, 3): the start of a control period."""
    imu_site_state_into(
        v0, r0, cvel, site_xpos, site_xmat, subtree_com, imu_index[0], imu_index[1],
        imu_index[2],
    )  # fmt: skip


@njit(cache=True)
def read_into(v0, r0, dt_s, cvel, site_xpos, site_xmat, subtree_com, imu_index, sensordata,
              joint_adr, pos_adr, quat_adr, noise, fix, rows, accel, gyro, joints, pos, quat,
              has_imu, has_fix):  # fmt: skip
    """``noisy_readings`` of the H robots in the world written into rows ``rows`` (H,) of the
    (N, ...) readings ``accel``, ``gyro``, ``joints``, ``pos``, ``quat``, ``has_imu`` and
    ``has_fix`` (every IMU frame arrives; a fix where ``fix``); the other rows are cleared.
    The IMU states now replace ``v0`` and ``r0``: the start of the next period."""
    v1, r1 = imu_site_state(
        cvel, site_xpos, site_xmat, subtree_com, imu_index[0], imu_index[1], imu_index[2]
    )
    accel[:], gyro[:], joints[:], pos[:], quat[:] = 0.0, 0.0, 0.0, 0.0, 0.0
    has_imu[:], has_fix[:] = False, False
    _readings_into(
        v0, r0, v1, r1, dt_s, sensordata, joint_adr, pos_adr, quat_adr, noise, fix, rows, accel,
        gyro, joints, pos, quat,
    )  # fmt: skip
    for k in range(rows.shape[0]):
        has_imu[rows[k]], has_fix[rows[k]] = True, fix
    v0[:] = v1
    r0[:] = r1


# Noise draws per robot and reading, in the order they are drawn: (name, size).
_NOISE_DRAWS = (("accel", 3), ("gyro", 3), ("joints", 2))
_FIX_DRAWS = (("position", 3), ("attitude", 3))


class NormalStream:
    """A generator's standard normals, drawn ahead in blocks of ``block`` and handed out in
    order: the same numbers as drawing each request from the generator itself (NumPy's
    ``standard_normal`` keeps no state between calls but the bit generator's). The generator is
    ahead of what was handed out, so nothing else may draw from it."""

    def __init__(self, rng: np.random.Generator, block: int = 2048) -> None:
        self.rng, self.block = rng, block
        self._normals, self._next = np.empty(0), 0

    def take(self, n: int) -> np.ndarray:
        """The next ``n`` standard normals (n,), a view that no later call overwrites."""
        start = self._next
        if start + n > self._normals.shape[0]:
            left = self._normals[start:]
            self._normals = np.empty(max(self.block, n))
            self._normals[: left.shape[0]] = left
            self.rng.standard_normal(out=self._normals[left.shape[0] :])
            start = 0
        self._next = start + n
        return self._normals[start : start + n]


class SensorSuite:
    """Reads every robot's sensors from ``data`` and adds the profile's noise.

    The robots' noise is drawn in one call, robot after robot in the order of ``_NOISE_DRAWS``
    (then ``_FIX_DRAWS`` at a localization fix): the same stream of numbers as one draw per
    reading. Every draw comes from ``normals``, the stream of the generator ``rng`` (or the
    ``NormalStream`` given: a suite rebuilt after a release continues its predecessor's).
    """

    def __init__(
        self, world: World, profile: NoiseProfile, rng: np.random.Generator | NormalStream
    ) -> None:
        self.world = world
        self.profile = profile
        self.normals = rng if isinstance(rng, NormalStream) else NormalStream(rng)
        robots = world.robots
        model = world.model
        self._imu_sites = np.array([h.imu_site for h in robots], dtype=np.int64)
        self._imu_bodies = model.site_bodyid[self._imu_sites].astype(np.int64)
        self._imu_roots = model.body_rootid[self._imu_bodies].astype(np.int64)
        adr = [h.sensor_adr for h in robots]
        self.joint_adr = np.array([[a["tilt_pos"], a["pan_pos"]] for a in adr], dtype=np.int64)
        self.pos_adr = np.array([a["base_pos"] + np.arange(3) for a in adr], dtype=np.int64)
        self.quat_adr = np.array([a["base_quat"] + np.arange(4) for a in adr], dtype=np.int64)
        # The IMUs' bodies, their roots and sites (3, n), as read_into and imu_state_into take.
        self.imu_index = np.array([self._imu_bodies, self._imu_roots, self._imu_sites])
        p = profile
        draws = _NOISE_DRAWS + _FIX_DRAWS
        self.noise_std = np.repeat(
            [p.accel_std, p.gyro_std, p.encoder_std_rad, p.position_std_m, p.attitude_std_rad],
            [size for _, size in draws],
        )
        self._n_draws = sum(size for _, size in _NOISE_DRAWS)
        self._n_draws_fix = sum(size for _, size in draws)
        # draw_step's count, without and with a fix.
        self._step_draws = {
            fix: len(self._imu_sites) * (6 + n)
            for fix, n in ((False, self._n_draws), (True, self._n_draws_fix))
        }
        self._actuation_abs = np.repeat([p.force_std_n, p.torque_std_nm], 3)
        self._actuation_rel = np.repeat([p.force_rel, p.torque_rel], 3)
        self.actuation_std = np.array([self._actuation_abs, self._actuation_rel])  # (2, 6)
        self._start: tuple[np.ndarray, np.ndarray, float] | None = None

    def _imu_state(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray, float]:
        """Every robot's IMU site: linear velocity (n, 3) in world axes, rotation (n, 3, 3) in
        the world, and the time."""
        vel, rot = imu_site_state(
            data.cvel, data.site_xpos, data.site_xmat, data.subtree_com, self._imu_bodies,
            self._imu_roots, self._imu_sites,
        )  # fmt: skip
        return vel, rot, float(data.time)

    def begin_period(self, data: mujoco.MjData) -> None:
        """Mark the start of a control period (``data`` after ``mj_forward``)."""
        self._start = self._imu_state(data)

    def read(self, data: mujoco.MjData, step: int) -> list[SensorPacket]:
        """Readings of all robots at the end of control period ``step`` (``data`` after
        ``mj_forward``, with ``begin_period`` called at the period's start)."""
        readings = self.read_arrays(data, step)
        return [readings.packet(k) for k in range(len(readings.has_imu))]

    def draw_noise(self, fix: bool) -> np.ndarray:
        """The noise of one reading of every robot (n, draws), ``_NOISE_DRAWS`` then, at a
        localization fix, ``_FIX_DRAWS``: standard deviation times a standard normal."""
        n_draws = self._n_draws_fix if fix else self._n_draws
        n = len(self._imu_sites)
        return self.noise_std[:n_draws] * self.normals.take(n * n_draws).reshape(n, n_draws)

    def draw_step(self, fix: bool) -> np.ndarray:
        """One control step's standard normals in one draw (n (6 + draws),): the propulsion's
        (n, 6) (``command_period``'s, drawn as ``actuate`` draws them), then the readings'
        (n, draws) that ``draw_noise(fix)`` scales by ``noise_std``; the same stream as the two
        draws in that order."""
        return self.normals.take(self._step_draws[fix])

    def read_into(self, views: tuple, time_s: float, fix: bool, start: tuple,
                  rows: np.ndarray, out: SensorReadings) -> None:  # fmt: skip
        """``read_arrays``' numbers at ``time_s`` written into ``out`` (one row per robot index;
        the robots of this world in ``rows``) from ``views`` (the data's cvel, site_xpos,
        site_xmat, subtree_com, sensordata), for a period that began at ``start`` (the IMUs'
        velocities (n, 3) and rotations (n, 3, 3), ``imu_state_into``, and the time; the first
        two are overwritten with the IMU states now, the next period's start); the noise is
        drawn here."""
        v0, r0, t0 = start
        cvel, site_xpos, site_xmat, subtree_com, sensordata = views
        out.time_s = time_s
        read_into(
            v0, r0, time_s - t0, cvel, site_xpos, site_xmat, subtree_com, self.imu_index,
            sensordata, self.joint_adr, self.pos_adr, self.quat_adr, self.draw_noise(fix),
            fix, rows, out.accel_imu, out.gyro_imu, out.joint_pos_rad, out.base_pos_world,
            out.base_quat_world, out.has_imu, out.has_fix,
        )  # fmt: skip

    def read_arrays(self, data: mujoco.MjData, step: int) -> SensorReadings:
        """``read``'s readings as arrays, one row per robot (the same numbers)."""
        p = self.profile
        fix = step % p.localization_every == 0
        n = len(self._imu_sites)
        if self._start is None or len(self._start[0]) != n:
            raise ValueError("read() needs begin_period() at the start of the period")
        v0, r0, t0 = self._start
        time_s = float(data.time)
        if time_s <= t0:
            raise ValueError("read() needs begin_period() at the start of the period")
        noise = self.draw_noise(fix)
        readings = noisy_readings(
            v0, r0, time_s - t0, data.cvel, data.site_xpos, data.site_xmat, data.subtree_com,
            self._imu_bodies, self._imu_roots, self._imu_sites, data.sensordata,
            self.joint_adr, self.pos_adr, self.quat_adr, noise, fix,
        )  # fmt: skip
        has_imu = np.ones(n, dtype=np.bool_)
        has_fix = has_imu.copy() if fix else np.zeros(n, dtype=np.bool_)
        return SensorReadings(time_s, *readings, has_imu, has_fix)

    def actuate(self, command: np.ndarray) -> np.ndarray:
        """The propulsion wrench actually delivered for a commanded one (..., 6): command plus
        absolute and command-proportional white noise (the robot knows only the command)."""
        command = np.asarray(command, dtype=float)
        std = self._actuation_abs + self._actuation_rel * np.abs(command)
        return command + std * self.normals.take(command.size).reshape(command.shape)
