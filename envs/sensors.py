"""What each robot senses, and the seeded noise on it.

Readings come from the MJCF sensors of each robot (``imu_accel``, ``imu_gyro`` at the IMU site,
``base_pos`` / ``base_quat`` of the base body, ``tilt_pos`` / ``pan_pos`` encoders) and must be read
after ``mj_forward`` so they describe the current state (pitfalls: after ``mj_step`` they lag one
step). The MJCF ``noise`` attribute does nothing at run time, so noise is added here from the env's
``np.random.Generator``. Nothing of the cargo is sensed.

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
    accel_imu: np.ndarray  # (3,) m/s^2, IMU frame
    gyro_imu: np.ndarray  # (3,) rad/s, IMU frame
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


class SensorSuite:
    """Reads every robot's sensors from ``data`` and adds the profile's noise."""

    def __init__(self, world: World, profile: NoiseProfile, rng: np.random.Generator) -> None:
        self.world = world
        self.profile = profile
        self.rng = rng

    def read(self, data: mujoco.MjData, step: int) -> list[SensorPacket]:
        """Readings of all robots at control step ``step`` (``data`` after ``mj_forward``)."""
        p = self.profile
        fix = step % p.localization_every == 0
        packets = []
        for h in self.world.robots:
            adr = h.sensor_adr
            s = data.sensordata
            accel = s[
                adr["imu_accel"] : adr["imu_accel"] + 3
            ] + p.accel_std * self.rng.standard_normal(3)
            gyro = s[adr["imu_gyro"] : adr["imu_gyro"] + 3] + p.gyro_std * self.rng.standard_normal(
                3
            )
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
