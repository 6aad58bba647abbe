"""What each robot senses, and the seeded noise on it.

Readings come from the MJCF sensors of each robot (``imu_accel``, ``imu_gyro`` at the IMU site,
``base_pos`` / ``base_quat`` of the base body, ``tilt_pos`` / ``pan_pos`` encoders) and must be read
after ``mj_forward`` so they describe the current state (pitfalls: after ``mj_step`` they lag one
step). The MJCF ``noise`` attribute does nothing at run time, so noise is added here from the env's
``np.random.Generator``. Nothing of the cargo is sensed.

IMU readings are averages over the control period (``begin_period`` marks its start): the change of
the IMU point's velocity over the period divided by its length, and the rotation over the period
as a mean rate. The Epson G362P averages internally (64-tap moving average at 125 samples/s, facts
file section 4.1), and a point sample would alias the arm servos' intra-period acceleration pattern
(it repeats at exactly the 62.5 Hz sample rate) into a bias that no low-pass filter removes.

Frames: accelerometer (specific force = acceleration in microgravity, m/s^2) and gyro (rad/s) in
the IMU frame; localization pose of the base frame in the module (world) frame, quaternion
(w, x, y, z); joint angles in rad.

Noise profiles (white, per 62.5 Hz sample, after the IMU's internal filtering). ``nominal`` uses the
floors of DESIGN.md "Estimation model": accelerometer 1e-3 m/s^2 and gyro 2e-4 rad/s (Epson
G362-class MEMS IMU; the Astrobee IMU is an Epson G362P, facts file section 4.1), localization 5 mm
and 0.2 deg at 62.5 / 20 = 3.125 Hz (the simulator's sparse-map features arrive at 3 Hz, facts
section 4.2), encoders 1e-3 rad, actuation 0.005 N + 2 % of the command and 5e-4 N m + 2 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from astrocargo.envs.world import World


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


@dataclass(frozen=True)
class SensorPacket:
    """One robot's readings at one control step."""

    time_s: float
    accel_imu: np.ndarray | None  # (3,) m/s^2, IMU frame; None: the frame is missing (a fault)
    gyro_imu: np.ndarray | None  # (3,) rad/s, IMU frame; None with accel_imu
    joint_pos_rad: np.ndarray  # (n_joints,)
    base_pos_world: np.ndarray | None  # (3,) m, only at a localization fix
    base_quat_world: np.ndarray | None  # (4,) w x y z, only at a localization fix


def _perturb_quat(quat: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    dq = np.empty(4)
    mujoco.mju_axisAngle2Quat(
        dq, rotvec / max(np.linalg.norm(rotvec), 1e-300), np.linalg.norm(rotvec)
    )
    out = np.empty(4)
    mujoco.mju_mulQuat(out, quat, dq)
    return out


def _rotvec_quat(rotvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rotvec)
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    if angle > 0:
        mujoco.mju_axisAngle2Quat(quat, rotvec / angle, angle)
    return quat


class SensorSuite:
    """Reads every robot's sensors from ``data`` and adds the profile's noise."""

    def __init__(self, world: World, profile: NoiseProfile, rng: np.random.Generator) -> None:
        self.world = world
        self.profile = profile
        self.rng = rng
        self._start: list[tuple[np.ndarray, np.ndarray, float]] = []

    def _imu_state(self, data: mujoco.MjData) -> list[tuple[np.ndarray, np.ndarray, float]]:
        out = []
        vel = np.zeros(6)
        for h in self.world.robots:
            mujoco.mj_objectVelocity(
                self.world.model, data, mujoco.mjtObj.mjOBJ_SITE, h.imu_site, vel, 0
            )
            rot = data.site_xmat[h.imu_site].reshape(3, 3).copy()
            out.append((vel[3:].copy(), rot, float(data.time)))
        return out

    def begin_period(self, data: mujoco.MjData) -> None:
        """Mark the start of a control period (``data`` after ``mj_forward``)."""
        self._start = self._imu_state(data)

    def _imu_means(self, data: mujoco.MjData) -> list[tuple[np.ndarray, np.ndarray]]:
        """Mean specific force and angular rate over the period, IMU frame."""
        out = []
        for (v0, r0, t0), (v1, r1, t1) in zip(self._start, self._imu_state(data), strict=True):
            dt = t1 - t0
            if dt <= 0:
                raise ValueError("read() needs begin_period() at the start of the period")
            rel = np.zeros(4)
            mujoco.mju_mat2Quat(rel, (r0.T @ r1).reshape(9))
            rotvec = np.zeros(3)
            mujoco.mju_quat2Vel(rotvec, rel, 1.0)
            half = np.zeros(9)
            mujoco.mju_quat2Mat(half, _rotvec_quat(0.5 * rotvec))
            r_mid = r0 @ half.reshape(3, 3)
            out.append((r_mid.T @ (v1 - v0) / dt, rotvec / dt))
        return out

    def read(self, data: mujoco.MjData, step: int) -> list[SensorPacket]:
        """Readings of all robots at the end of control period ``step`` (``data`` after
        ``mj_forward``, with ``begin_period`` called at the period's start)."""
        p = self.profile
        fix = step % p.localization_every == 0
        if len(self._start) != len(self.world.robots):
            raise ValueError("read() needs begin_period() at the start of the period")
        packets = []
        means = self._imu_means(data)
        for h, (accel_mean, gyro_mean) in zip(self.world.robots, means, strict=True):
            adr = h.sensor_adr
            s = data.sensordata
            accel = accel_mean + p.accel_std * self.rng.standard_normal(3)
            gyro = gyro_mean + p.gyro_std * self.rng.standard_normal(3)
            joints = np.array([s[adr["tilt_pos"]], s[adr["pan_pos"]]])
            joints = joints + p.encoder_std_rad * self.rng.standard_normal(joints.shape)
            pos = quat = None
            if fix:
                pos = s[
                    adr["base_pos"] : adr["base_pos"] + 3
                ] + p.position_std_m * self.rng.standard_normal(3)
                quat = _perturb_quat(
                    s[adr["base_quat"] : adr["base_quat"] + 4].copy(),
                    p.attitude_std_rad * self.rng.standard_normal(3),
                )
            packets.append(
                SensorPacket(
                    time_s=float(data.time),
                    accel_imu=accel,
                    gyro_imu=gyro,
                    joint_pos_rad=joints,
                    base_pos_world=pos,
                    base_quat_world=quat,
                )
            )
        return packets

    def actuate(self, command: np.ndarray) -> np.ndarray:
        """The propulsion wrench actually delivered for a commanded one (..., 6): command plus
        absolute and command-proportional white noise (the robot knows only the command)."""
        p = self.profile
        command = np.asarray(command, dtype=float)
        std = np.concatenate(
            (
                p.force_std_n + p.force_rel * np.abs(command[..., :3]),
                p.torque_std_nm + p.torque_rel * np.abs(command[..., 3:]),
            ),
            axis=-1,
        )
        return command + std * self.rng.standard_normal(command.shape)
