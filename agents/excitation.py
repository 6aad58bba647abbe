"""Excitation designed for information: a windowed finite Fourier series of the cargo's motion and
of the arms' pan, optimised on the Fisher information the project's own estimator would get,
within the robots' propulsion limits, the servo's range and rate and the module's walls.

Parameterisation (Swevers et al. 1997, a finite Fourier series per degree of freedom, here
windowed so that the motion starts and ends at rest): seven degrees of freedom d, the cargo
reference's position offset (x, y, z; m, module frame), its attitude as Z-X-Y angles
R = Rz(yaw) Rx(roll) Ry(pitch) (rad, as ``figure8_tumble``), and the pan angle of every robot's
arm (rad, one angle for the team: the controller and the env's reference carry one pan):

    q_d(t) = s(t) f_d(t),  f_d(t) = sum_k=1..K a_dk sin(k w0 t) + b_dk cos(k w0 t),  w0 = 2 pi / T0,

with s(t) the window rising from 0 to 1 over [0, T_r] and falling back over [T - T_r, T] (a
quintic smoothstep: s, s', s'' vanish at both ends), so q, q' and q'' are zero at t = 0 and
t = T: the cargo starts and ends at rest at the module centre, aligned, arms deployed.

What the estimator sees (``estimator.cargo_estimator``): per update instant k (every
``update_every`` control steps after ``warmup_s``) the wrench balance in robot 0's grasp frame G,
z_k = A_k pi + b_k + e_k, with A_k = ``rne.body_regressor`` of G's motion (G is fixed to the
cargo: its acceleration, angular velocity and acceleration follow from the cargo's) and e_k of
covariance R_k = meas_cov + (sum_j M_j diag(s_j^2) M_j^T) / update_every + sensor_cov, where
s_j = abs + rel |u_j| is robot j's actuation noise per axis at its command u_j, M_j carries it
into G (``grasp_from_base`` of the thrust site; peers through the known relative grasp) and
sensor_cov is the estimator's errors-in-variables term at the design cargo. The Fisher
information F = sum_k A_k^T R_k^-1 A_k and the Cramer-Rao bounds of mass, centre of mass and
principal moments (``baselines.derived_covariance``) are what ``scripts/benchmark_estimation.py``
computes from a flight's recording.

Commands u_j: the robots and the cargo move as one rigid body (the pan is slow); the wrench the
planned motion needs about the composite centre of mass, M (a + wd x r + w x (w x r)) and
I_c wd + w x I_c w (cargo axes), is shared by ``CooperativeController``'s allocation (minimum norm
weighted by each robot's limits) on the design cargo, at the planned pan.

Objective: the worst of log(bound_i / target_i) over the three principal moments (relative),
the mass (relative) and the centre of mass (norm of the per-axis bounds, m), minimised in
epigraph form (minimise z subject to log(bound_i / target_i) <= z), a minimax. Constraints, at
every sample of a time grid: every robot's command per axis within (1 - ``thrust_margin``) of
its limit (the rest is left to the feedback), every point of the assembly's collision hull
``clearance_m`` inside the aisle's walls, pan within its range and its rate within
``pan_rate_margin`` of the servo's 0.12 rad/s. Solved by SLSQP (scipy) with forward-difference
Jacobians from several random starts, each first scaled down until it is feasible; the best
design is scaled down, if need be, until every constraint holds on a 0.1 s grid.

Spins: besides the series, each attitude angle may carry a secular rate Omega_d windowed like
the series (angle += Omega_d S(t), S the window's integral): a spin that starts and ends at
rest (not at the start attitude).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import ConvexHull

from astrocargo.estimator.baselines import derived_quantities
from astrocargo.estimator.cargo_estimator import CargoEstimator
from astrocargo.estimator.geometry import quat_to_mat
from astrocargo.estimator.inertia import (
    mass_com_inertia_from_params,
    params_from_mass_com_inertia,
    principal_moments,
    transform_params,
)
from astrocargo.estimator.rne import (
    RobotDescription,
    body_regressor,
    grasp_from_base,
    grasp_pose,
    link_poses,
    wrench_transform,
)

from .trajectories import Reference, ReferenceValues

DOF_NAMES = ("x", "y", "z", "yaw", "roll", "pitch", "pan")
N_DOF = len(DOF_NAMES)
PAN_DOF = 6
SERVO_RATE_RADPS = 0.12  # URDF joint velocity limit (sources §5, docs/design.md)
PAN_RANGE_RAD = 0.5  # the env's pan action scale: target = a * 0.5 rad, a in [-1, 1]
TILT_DEPLOYED_RAD = -np.pi / 2
# Bound targets of the issue (1 sigma): principal moments 3.5 %, mass 0.8 %, centre of mass 3 mm.
TARGETS = {"principal_rel": 0.035, "mass_rel": 0.008, "com_m": 0.003}
DESIGN_VERSION = 1
# Designs shipped with the package, one per team size: excite_<n>robots.json.
DESIGNS_DIR = Path(__file__).resolve().parent / "designs"


# ------------------------------------------------------------------------------- the motion
def window(t: np.ndarray, duration_s: float, ramp_s: float) -> tuple[np.ndarray, ...]:
    """s(t), s'(t), s''(t): 0 -> 1 over [0, ramp] (quintic smoothstep), 1, then 1 -> 0 over
    [duration - ramp, duration], 0 outside [0, duration]."""
    t = np.asarray(t, dtype=float)

    def rise(x):
        x = np.clip(x, 0.0, 1.0)
        return (
            x**3 * (10 - 15 * x + 6 * x * x),
            30 * x * x * (1 - x) ** 2 / ramp_s,
            60 * x * (1 - x) * (1 - 2 * x) / ramp_s**2,
        )

    up, up_d, up_dd = rise(t / ramp_s)
    down, down_d, down_dd = rise((duration_s - t) / ramp_s)
    # s = up * down (the ramps do not overlap when duration >= 2 ramp); down's time runs backwards.
    s = up * down
    sd = up_d * down - up * down_d
    sdd = up_dd * down - 2 * up_d * down_d + up * down_dd
    return s, sd, sdd


def window_integral(t: np.ndarray, duration_s: float, ramp_s: float) -> np.ndarray:
    """S(t) = integral of ``window`` from 0 to t (s): U(t) while the window rises or holds,
    (T - ramp) - U(T - t) while it falls, with U(u) = ramp x^4 (5/2 - 3 x + x^2), x = u / ramp,
    for u < ramp and u - ramp / 2 after."""
    t = np.clip(np.asarray(t, dtype=float), 0.0, duration_s)

    def rise_integral(u):
        x = np.clip(u / ramp_s, 0.0, 1.0)
        return ramp_s * x**4 * (2.5 - 3 * x + x * x) + np.maximum(u - ramp_s, 0.0)

    falling = t > duration_s - ramp_s
    return np.where(
        falling,
        duration_s - ramp_s - rise_integral(duration_s - t),
        rise_integral(t),
    )


def _rot_axis(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) by ``angle`` (N,) about axis 0, 1 or 2."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.zeros((angle.size, 3, 3))
    r[:, axis, axis] = 1.0
    r[:, i, i] = r[:, j, j] = c
    r[:, i, j], r[:, j, i] = -s, s
    return r


@dataclass(frozen=True)
class Motion:
    """The planned motion on a time grid (N samples): cargo reference (world axes) and pan."""

    t: np.ndarray
    pos: np.ndarray  # (N, 3) m
    vel: np.ndarray
    acc: np.ndarray
    rot: np.ndarray  # (N, 3, 3) cargo frame in world
    w: np.ndarray  # (N, 3) rad/s, world axes
    wd: np.ndarray
    pan: np.ndarray  # (N,) rad
    pan_rate: np.ndarray
    pan_acc: np.ndarray


def fourier_dofs(
    coeffs: np.ndarray, period_s: float, duration_s: float, ramp_s: float, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q, q', q'' (n_dof, N) of the windowed Fourier series (module docstring); ``coeffs``
    (n_dof, 2K): sine amplitudes of harmonics 1..K, then cosine amplitudes."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    coeffs = np.asarray(coeffs, dtype=float)
    n_harm = coeffs.shape[1] // 2
    k_w = 2 * np.pi / period_s * np.arange(1, n_harm + 1)  # (K,)
    phase = np.outer(k_w, t)  # (K, N)
    sn, cs = np.sin(phase), np.cos(phase)
    a, b = coeffs[:, :n_harm], coeffs[:, n_harm:]
    f = a @ sn + b @ cs
    fd = (a * k_w) @ cs - (b * k_w) @ sn
    fdd = -((a * k_w**2) @ sn + (b * k_w**2) @ cs)
    s, sd, sdd = window(t, duration_s, ramp_s)
    return s * f, sd * f + s * fd, sdd * f + 2 * sd * fd + s * fdd


def attitude_zxy(angles: np.ndarray, rates: np.ndarray, accs: np.ndarray) -> tuple[np.ndarray, ...]:
    """R = Rz(yaw) Rx(roll) Ry(pitch) and its angular velocity and acceleration in world axes,
    from (yaw, roll, pitch) (3, N) and their first and second derivatives:
    w = yaw' e_z + roll' e_x + pitch' e_y with e_x = Rz e1, e_y = Rz Rx e2, and
    wd = yaw'' e_z + roll'' e_x + roll' (w_z x e_x) + pitch'' e_y + pitch' ((w_z + w_x) x e_y)."""
    (yaw, roll, pitch), (yaw_d, roll_d, pitch_d), (yaw_dd, roll_dd, pitch_dd) = angles, rates, accs
    rz = _rot_axis(2, yaw)
    rzx = rz @ _rot_axis(0, roll)
    rot = rzx @ _rot_axis(1, pitch)
    ez = np.broadcast_to(np.array([0.0, 0.0, 1.0]), rz[:, :, 0].shape)
    ex, ey = rz[:, :, 0], rzx[:, :, 1]
    w_z, w_x = yaw_d[:, None] * ez, roll_d[:, None] * ex
    w = w_z + w_x + pitch_d[:, None] * ey
    wd = (
        yaw_dd[:, None] * ez
        + roll_dd[:, None] * ex
        + roll_d[:, None] * np.cross(w_z, ex)
        + pitch_dd[:, None] * ey
        + pitch_d[:, None] * np.cross(w_z + w_x, ey)
    )
    return rot, w, wd


@dataclass(frozen=True)
class ExcitationDesign:
    """A designed excitation: the Fourier coefficients and their timing, with what the designer
    predicted and the limits it was designed for (``info``). JSON round-trips exactly."""

    coeffs: np.ndarray  # (7, 2K), m and rad (DOF_NAMES)
    period_s: float
    duration_s: float
    ramp_s: float
    n_robots: int
    center_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    info: dict = field(default_factory=dict)
    # Secular rates (rad/s) of (yaw, roll, pitch), windowed like the series: spins.
    spin_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        c = np.asarray(self.coeffs, dtype=float)
        if c.ndim != 2 or c.shape[0] != N_DOF or c.shape[1] < 2 or c.shape[1] % 2:
            raise ValueError(f"coeffs must be ({N_DOF}, 2K) with K >= 1, got shape {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("coeffs must be finite")
        if not (self.period_s > 0 and self.ramp_s > 0 and self.duration_s >= 2 * self.ramp_s):
            raise ValueError(
                f"need period_s > 0, ramp_s > 0 and duration_s >= 2 ramp_s, got "
                f"{self.period_s}, {self.ramp_s}, {self.duration_s}"
            )
        object.__setattr__(self, "coeffs", c)
        spin = tuple(float(x) for x in self.spin_radps)
        if len(spin) != 3 or not all(math.isfinite(x) for x in spin):
            raise ValueError(f"spin_radps must be 3 finite rates, got {self.spin_radps!r}")
        object.__setattr__(self, "spin_radps", spin)

    def to_dict(self) -> dict:
        return {
            "kind": "astrocargo.excitation",
            "version": DESIGN_VERSION,
            "dof_names": list(DOF_NAMES),
            "coeffs": self.coeffs.tolist(),
            "period_s": self.period_s,
            "duration_s": self.duration_s,
            "ramp_s": self.ramp_s,
            "n_robots": self.n_robots,
            "center_m": list(self.center_m),
            "spin_radps": list(self.spin_radps),
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ExcitationDesign:
        if d.get("kind") != "astrocargo.excitation":
            raise ValueError("not an excitation design (kind != 'astrocargo.excitation')")
        if tuple(d.get("dof_names", ())) != DOF_NAMES:
            raise ValueError(f"design degrees of freedom must be {DOF_NAMES}")
        return cls(
            np.array(d["coeffs"], dtype=float),
            float(d["period_s"]),
            float(d["duration_s"]),
            float(d["ramp_s"]),
            int(d["n_robots"]),
            tuple(float(x) for x in d["center_m"]),
            dict(d.get("info", {})),
            tuple(float(x) for x in d.get("spin_radps", (0.0, 0.0, 0.0))),
        )

    def save(self, path: str | Path) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> ExcitationDesign:
        return cls.from_dict(json.loads(Path(path).read_text()))


def shipped_design(n_robots: int) -> ExcitationDesign:
    """The design shipped for a team of ``n_robots`` (``DESIGNS_DIR``); ``ValueError`` if none."""
    path = DESIGNS_DIR / f"excite_{int(n_robots)}robots.json"
    if not path.exists():
        have = sorted(p.name for p in DESIGNS_DIR.glob("excite_*robots.json"))
        raise ValueError(f"no excitation design shipped for {n_robots} robots; shipped: {have}")
    design = ExcitationDesign.load(path)
    if design.n_robots != n_robots:
        raise ValueError(f"{path.name} was designed for {design.n_robots} robots, not {n_robots}")
    return design


class DesignedTrajectory:
    """A designed excitation as a cargo reference, with ``Trajectory``'s interface:
    ``traj(t)`` -> ``Reference``, ``values(t)`` -> ``ReferenceValues`` (floats), ``motion(t)``
    on a time grid. After ``duration_s`` it holds the start pose at rest."""

    NAMES = ("excite",)

    def __init__(self, design: ExcitationDesign) -> None:
        self.design = design
        self.name = "excite"
        self.fast = False
        self.center = np.asarray(design.center_m, dtype=float)
        self.pan_ramp = True

    def motion(self, t: np.ndarray) -> Motion:
        d = self.design
        t = np.atleast_1d(np.asarray(t, dtype=float))
        q, qd, qdd = fourier_dofs(d.coeffs, d.period_s, d.duration_s, d.ramp_s, t)
        if any(d.spin_radps):
            spin = np.asarray(d.spin_radps)[:, None]
            s, sd, _ = window(t, d.duration_s, d.ramp_s)
            q[3:6] += spin * window_integral(t, d.duration_s, d.ramp_s)
            qd[3:6] += spin * s
            qdd[3:6] += spin * sd
        rot, w, wd = attitude_zxy(q[3:6], qd[3:6], qdd[3:6])
        return Motion(
            t,
            self.center + q[:3].T,
            qd[:3].T,
            qdd[:3].T,
            rot,
            w,
            wd,
            q[PAN_DOF],
            qd[PAN_DOF],
            qdd[PAN_DOF],
        )

    def values(self, t: float) -> ReferenceValues:
        m = self.motion(np.array([float(t)]))
        return ReferenceValues(
            m.pos[0].tolist(),
            m.vel[0].tolist(),
            m.acc[0].tolist(),
            m.rot[0].tolist(),
            m.w[0].tolist(),
            m.wd[0].tolist(),
            float(m.pan[0]),
            float(m.pan_rate[0]),
        )

    def arrays(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference at ``t`` as ``Trajectory.arrays`` gives it: rotation (3, 3); pos, vel,
        acc, w, wd as the rows of a (5, 3), world axes; (pan, pan_rate) (2,)."""
        m = self.motion(np.array([float(t)]))
        vecs = np.stack((m.pos[0], m.vel[0], m.acc[0], m.w[0], m.wd[0]))
        return np.ascontiguousarray(m.rot[0]), vecs, np.array((m.pan[0], m.pan_rate[0]))

    def __call__(self, t: float) -> Reference:
        return self.values(t).to_reference()


# ------------------------------------------------------------------------------- ESTIMATOR COUPLING
# The ONE place that reads CargoEstimator's private noise model (meas_cov, _actuation_abs/_rel,
# _acc_noise, _ang_acc_noise, _joint_acc_noise, _robot_mass, _robot_inertia, _correlated: the
# terms of CargoEstimator.process's meas_cov and of CargoEstimator._sensor_cov). When the
# estimator offers a public method for its per-update measurement covariance, repoint this
# function to it; nothing else in this module depends on how R is built.
def estimator_measurement_cov(
    estimator: CargoEstimator,
    cargo_grasp: np.ndarray,
    commands: np.ndarray,
    noise_maps: np.ndarray,
    lever_m: np.ndarray,
) -> np.ndarray:
    """R_k (N, 6, 6) of the estimator's update at each of N samples, robot 0's grasp frame:

        R_k = meas_cov + (sum_j M_j diag(s_j^2) M_j^T) / update_every + c diag(F, F, F, N, N, N),

    s_j = abs + rel |u_j| robot j's actuation noise per axis at its command ``commands``
    (N, n, 6) [N; N m], M_j = ``noise_maps`` (N, n, 6, 6) (thrust site -> robot 0's grasp
    frame), and the errors-in-variables term at the cargo ``cargo_grasp`` (10,) (grasp frame) as
    its estimate and base-to-grasp lever ``lever_m`` (N,) m: F = (M a)^2 + (m_c L q)^2,
    N = (J wd)^2 + (M L a)^2 + (m_c |c| L q)^2, with M the robot-plus-cargo mass (kg), J the
    inertia about the grasp (kg m^2), a, wd, q the accelerometer, angular-acceleration and
    joint-acceleration noise after the estimator's filters, c its correlation factor."""
    est = estimator
    std = est._actuation_abs + est._actuation_rel * np.abs(commands)  # (N, n, 6)
    act = np.einsum("nkij,nkj,nklj->nil", noise_maps, std**2, noise_maps)
    m_c, h_x, h_y, h_z, i_xx, i_yy, i_zz = (float(x) for x in cargo_grasp[:7])
    com = math.sqrt(h_x * h_x + h_y * h_y + h_z * h_z) / m_c
    lever = np.asarray(lever_m, dtype=float)
    total = est._robot_mass + m_c
    inertia = est._robot_inertia + est._robot_mass * lever**2 + max(i_xx, i_yy, i_zz)
    force = (total * est._acc_noise) ** 2 + (m_c * lever * est._joint_acc_noise) ** 2
    moment = (
        (inertia * est._ang_acc_noise) ** 2
        + (total * lever * est._acc_noise) ** 2
        + (m_c * com * lever * est._joint_acc_noise) ** 2
    )
    sensor = np.zeros((lever.size, 6, 6))
    idx = np.arange(3)
    sensor[:, idx, idx] = force[:, None]
    sensor[:, idx + 3, idx + 3] = moment[:, None]
    return est.meas_cov + act / est.update_every + est._correlated * sensor


# ------------------------------------------------------------------------------- the model
def derived_jacobian(pi: np.ndarray, step: float = 1e-7) -> np.ndarray:
    """G = d g / d pi (7, 10) of ``baselines.derived_quantities`` (mass, centre of mass,
    principal moments) at pi, by the same central differences as ``baselines.derived_covariance``
    (which is G cov G^T)."""
    pi = np.asarray(pi, dtype=float)
    jac = np.zeros((7, pi.size))
    for i in range(pi.size):
        h = step * max(abs(pi[i]), 1e-3)
        d = np.zeros_like(pi)
        d[i] = h
        jac[:, i] = (derived_quantities(pi + d) - derived_quantities(pi - d)) / (2 * h)
    return jac


@dataclass(frozen=True)
class Limits:
    """What the design must respect (module docstring)."""

    thrust_margin: float = 0.25  # fraction of every axis's limit left to the feedback
    clearance_m: float = 0.15  # hull to walls
    pan_range_rad: float = PAN_RANGE_RAD
    pan_rate_radps: float = SERVO_RATE_RADPS
    pan_rate_margin: float = 0.15


class ExcitationModel:
    """The team, the design cargo, the estimator's measurement model and the limits: predicts
    the commands and the Fisher information of a planned motion.

    Args:
        robots: the robots' known models (robot i holds handrail i).
        handrail_poses: (rotation, position) of each robot's handrail (its grasp frame) in the
            cargo frame.
        cargo_params: the design ("prior") cargo's standard parameters in the cargo frame.
        dt_s: control period; ``estimator_kwargs``: the env's ``CargoEstimator`` settings (noise
            profile), from which robot 0's estimator is built for its measurement model.
        hull_points_m: (P, 3) points of the assembly's collision hull in the cargo frame (union
            over pan angles); ``aisle_half_m``: the free aisle's half extents (module frame).
        limits: ``Limits``; ``n_pan_grid``: pan angles at which the team geometry is tabulated
            (linear interpolation between them).
    """

    def __init__(
        self,
        robots: list[RobotDescription],
        handrail_poses: list[tuple[np.ndarray, np.ndarray]],
        cargo_params: np.ndarray,
        dt_s: float,
        estimator_kwargs: dict | None = None,
        hull_points_m: np.ndarray | None = None,
        aisle_half_m: np.ndarray | tuple[float, float, float] = (3.0, 1.1, 1.1),
        limits: Limits | None = None,
        n_pan_grid: int = 41,
    ) -> None:
        if len(robots) != len(handrail_poses) or not robots:
            raise ValueError("robots and handrail_poses must have one entry per robot (>= 1)")
        self.robots = list(robots)
        self.n_robots = len(robots)
        self.handrails = [(np.asarray(r, float), np.asarray(p, float)) for r, p in handrail_poses]
        self.cargo_params = np.asarray(cargo_params, dtype=float)
        if self.cargo_params.shape != (10,):
            raise ValueError(f"cargo_params must be (10,), got {self.cargo_params.shape}")
        self.dt_s = float(dt_s)
        self.limits = limits or Limits()
        hull = np.zeros((1, 3)) if hull_points_m is None else np.asarray(hull_points_m, float)
        if len(hull) > 4:
            # The farthest point along any direction is a vertex of the convex hull.
            hull = hull[ConvexHull(hull).vertices]
        self.hull = hull
        self.aisle_half = np.asarray(aisle_half_m, dtype=float)
        self.thrust_limit = np.stack([r.thrust_limit for r in self.robots])  # (n, 6)
        # Robot 0's estimator: the measurement model whose information is designed for.
        rot0, pos0 = self.handrails[0]
        relative = {
            j: (rot0.T @ rot_j, rot0.T @ (pos_j - pos0))
            for j, (rot_j, pos_j) in enumerate(self.handrails)
            if j
        }
        # Peer j's wrench into robot 0's grasp frame, the relative grasp the estimator is given.
        self.relative_known = {j: wrench_transform(rot, pos) for j, (rot, pos) in relative.items()}
        self.estimator = CargoEstimator(
            self.robots[0],
            0,
            list(relative),
            self.dt_s,
            relative_grasps=relative,
            **(estimator_kwargs or {}),
        )
        # The design cargo in robot 0's grasp frame (what its estimator estimates).
        self.cargo_grasp = transform_params(self.cargo_params, rot0.T, -rot0.T @ pos0)
        self.moments = principal_moments(mass_com_inertia_from_params(self.cargo_grasp)[2])
        self.derived_jacobian = derived_jacobian(self.cargo_grasp)
        self.pan_grid = np.linspace(
            -self.limits.pan_range_rad, self.limits.pan_range_rad, n_pan_grid
        )
        self._tabulate()

    # -------------------------------------------------------------- team geometry per pan
    def base_in_cargo(self, i: int, pan: float) -> tuple[np.ndarray, np.ndarray]:
        """Robot i's base pose (rotation, position) in the cargo frame at pan angle ``pan``."""
        rot_bg, pos_bg = grasp_pose(self.robots[i], np.array([TILT_DEPLOYED_RAD, pan]))
        rot_ch, pos_ch = self.handrails[i]
        rot_cb = rot_ch @ rot_bg.T
        return rot_cb, pos_ch - rot_cb @ pos_bg

    def _team_at(self, pan: float) -> dict:
        """Composite body, allocation and noise maps at one pan angle (cargo axes)."""
        total = self.cargo_params.copy()
        poses = [self.base_in_cargo(i, pan) for i in range(self.n_robots)]
        for robot, (rot_cb, pos_cb) in zip(self.robots, poses, strict=True):
            links = np.stack(
                [params_from_mass_com_inertia(k.mass, k.com, k.inertia_com) for k in robot.links]
            )
            rots, poss = link_poses(robot, np.array([TILT_DEPLOYED_RAD, pan]))
            total = total + transform_params(links, rot_cb @ rots, pos_cb + poss @ rot_cb.T).sum(0)
        mass, com, inertia = mass_com_inertia_from_params(total)
        # CooperativeController's allocation: u_i = W_i G_i^T (sum_j G_j W_j G_j^T)^-1 wrench.
        gs = [wrench_transform(rot, pos - com) for rot, pos in poses]
        ws = [np.diag(lim**2) for lim in self.thrust_limit]
        mat = sum(g @ w @ g.T for g, w in zip(gs, ws, strict=True))
        alloc = np.stack([w @ g.T @ np.linalg.inv(mat) for g, w in zip(gs, ws, strict=True)])
        # Actuation noise of robot j (thrust-site axes) into robot 0's grasp frame.
        noise_maps = []
        for j, robot in enumerate(self.robots):
            rot_bg, pos_bg = grasp_pose(robot, np.array([TILT_DEPLOYED_RAD, pan]))
            to_grasp = grasp_from_base(rot_bg, pos_bg) @ wrench_transform(
                robot.thrust_rot, robot.thrust_pos
            )
            noise_maps.append(to_grasp if j == 0 else self.relative_known[j] @ to_grasp)
        lever0 = float(
            np.linalg.norm(grasp_pose(self.robots[0], np.array([TILT_DEPLOYED_RAD, pan]))[1])
        )
        return {
            "mass": mass,
            "com": com,
            "inertia": inertia,
            "alloc": alloc,
            "noise": np.stack(noise_maps),
            "lever": lever0,
        }

    def _tabulate(self) -> None:
        tabs = [self._team_at(float(p)) for p in self.pan_grid]
        self._tab = {k: np.stack([np.asarray(t[k], float) for t in tabs]) for k in tabs[0]}

    def team(self, pan: np.ndarray) -> dict:
        """The tabulated team quantities at pan angles (N,) (linear interpolation)."""
        pan = np.clip(np.asarray(pan, float), self.pan_grid[0], self.pan_grid[-1])
        step = self.pan_grid[1] - self.pan_grid[0]
        x = (pan - self.pan_grid[0]) / step
        i = np.minimum(np.floor(x).astype(int), self.pan_grid.size - 2)
        frac = x - i
        out = {}
        for k, tab in self._tab.items():
            shape = (-1,) + (1,) * (tab.ndim - 1)
            out[k] = tab[i] * (1 - frac).reshape(shape) + tab[i + 1] * frac.reshape(shape)
        return out

    # -------------------------------------------------------------- predictions
    def commands(self, motion: Motion) -> np.ndarray:
        """Feed-forward commands (N, n_robots, 6) [N; N m] of the planned motion through the
        controller's allocation on the design cargo, each robot's base axes."""
        team = self.team(motion.pan)
        rot_t = np.swapaxes(motion.rot, 1, 2)
        acc = np.einsum("nij,nj->ni", rot_t, motion.acc)
        w = np.einsum("nij,nj->ni", rot_t, motion.w)
        wd = np.einsum("nij,nj->ni", rot_t, motion.wd)
        r = team["com"]
        force = team["mass"][:, None] * (acc + np.cross(wd, r) + np.cross(w, np.cross(w, r)))
        iw = np.einsum("nij,nj->ni", team["inertia"], w)
        torque = np.einsum("nij,nj->ni", team["inertia"], wd) + np.cross(w, iw)
        wrench = np.concatenate((force, torque), axis=1)
        return np.einsum("nkij,nj->nki", team["alloc"], wrench)

    def grasp_kinematics(self, motion: Motion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Acceleration of robot 0's grasp origin, angular velocity and acceleration, all in
        its grasp frame G (N, 3) each; G is fixed to the cargo."""
        rot_ch, pos_ch = self.handrails[0]
        rot_gw = np.swapaxes(motion.rot @ rot_ch, 1, 2)  # world -> G
        p = np.einsum("nij,j->ni", motion.rot, pos_ch)  # cargo origin -> grasp, world
        acc = motion.acc + np.cross(motion.wd, p) + np.cross(motion.w, np.cross(motion.w, p))
        return tuple(np.einsum("nij,nj->ni", rot_gw, v) for v in (acc, motion.w, motion.wd))

    def measurement_cov(self, motion: Motion, commands: np.ndarray) -> np.ndarray:
        """R (N, 6, 6) of the estimator's update at each sample (module docstring)."""
        team = self.team(motion.pan)
        return estimator_measurement_cov(
            self.estimator, self.cargo_grasp, commands, team["noise"], team["lever"]
        )

    def update_times(
        self, duration_s: float, every: int = 1
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Every ``every``-th update instant of the estimator from the start of the flight to
        its end: times, the weight (``every``) that makes a sum over them stand for all
        instants, and which of them the estimator uses (after its warm-up)."""
        est = self.estimator
        stamps = np.arange(0, int(round(duration_s / self.dt_s)) + 1, est.update_every * every)
        return stamps * self.dt_s, float(every), stamps >= est.warmup_steps

    def fisher(
        self, motion: Motion, weight: float = 1.0, commands: np.ndarray | None = None
    ) -> np.ndarray:
        """F = weight * sum_k A_k^T R_k^-1 A_k over the samples of ``motion`` (``commands``:
        ``self.commands(motion)`` if already computed)."""
        a = body_regressor(*self.grasp_kinematics(motion))
        cmd = self.commands(motion) if commands is None else commands
        r = self.measurement_cov(motion, cmd)
        return weight * np.einsum("kji,kjl->il", a, np.linalg.solve(r, a))

    def bounds(self, fisher: np.ndarray) -> dict:
        """Cramer-Rao bounds (1 sigma) at the design cargo: mass (relative), centre of mass
        (per axis and norm, m), principal moments (relative, ascending)."""
        scale = max(float(np.trace(fisher)), 1e-300) * 1e-12
        cov = np.linalg.inv(fisher + scale * np.eye(10))
        jac = self.derived_jacobian
        derived = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, cov, jac), 0.0))
        return {
            "mass_rel": float(derived[0] / self.cargo_grasp[0]),
            "com_m": float(np.linalg.norm(derived[1:4])),
            "com_axes_m": derived[1:4].tolist(),
            "principal_rel": (derived[4:7] / self.moments).tolist(),
        }

    def filtered_fisher(self, trajectory: DesignedTrajectory, duration_s: float) -> np.ndarray:
        """The Fisher information as the estimator builds it: the regressor evaluated every
        ``regressor_every`` control steps, low-passed by the estimator's own slow filter, taken
        at each update instant after warm-up whose excitation passes the estimator's test."""
        est = self.estimator
        n_steps = int(round(duration_s / self.dt_s))
        stamps = np.arange(0, n_steps + 1, est.regressor_every)
        motion = trajectory.motion(stamps * self.dt_s)
        regs = body_regressor(*self.grasp_kinematics(motion)).reshape(-1, 60)
        filt = copy.deepcopy(est.balance_filter)
        out = np.zeros_like(regs)
        for k, row in enumerate(regs):
            out[k] = filt.step(np.concatenate((np.zeros(12), row)))[0][12:]
        keep = (stamps % est.update_every == 0) & (stamps >= est.warmup_steps)
        a = out[keep].reshape(-1, 6, 10)
        # The estimator's own excitation test (CargoEstimator._excited at its grasp lever): a
        # second, read-only use of its internals, outside the measurement covariance.
        est._grasp_lever = float(
            np.linalg.norm(grasp_pose(self.robots[0], np.array([TILT_DEPLOYED_RAD, 0.0]))[1])
        )
        excited = np.array([est._excited(x) for x in a])
        sub = trajectory.motion(stamps[keep] * self.dt_s)
        r = self.measurement_cov(sub, self.commands(sub))
        a, r = a[excited], r[excited]
        return np.einsum("kji,kjl->il", a, np.linalg.solve(r, a))

    # -------------------------------------------------------------- limits
    def violations(self, motion: Motion, commands: np.ndarray | None = None) -> dict:
        """Normalised constraint values (<= 0 where satisfied), per group, one per sample."""
        lim = self.limits
        cmd = self.commands(motion) if commands is None else commands
        thrust = np.abs(cmd) / (self.thrust_limit * (1 - lim.thrust_margin)) - 1.0
        # Farthest hull point from the module centre per axis and sample.
        world = motion.pos[:, :, None] + motion.rot @ self.hull.T  # (N, 3, P)
        reach = np.abs(world).max(axis=2)
        wall = (reach + lim.clearance_m) / self.aisle_half - 1.0
        pan = np.abs(motion.pan) / lim.pan_range_rad - 1.0
        pan_rate = np.abs(motion.pan_rate) / (lim.pan_rate_radps * (1 - lim.pan_rate_margin)) - 1.0
        return {
            "thrust": thrust.reshape(len(motion.t), -1),
            "wall": wall.reshape(len(motion.t), -1),
            "pan": pan[:, None],
            "pan_rate": pan_rate[:, None],
        }


# ------------------------------------------------------------------------------- the designer
@dataclass(frozen=True)
class DesignSettings:
    """How the design is searched (module docstring)."""

    duration_s: float = 90.0
    n_harmonics: int = 4
    period_s: float | None = None  # None: duration / 2
    ramp_s: float = 10.0
    starts: int = 4
    seed: int = 0
    fd_step: float = 1e-5  # forward-difference step of the (scaled) variables
    start_std: float = 0.2  # random starts: normal variables of this spread
    safety: float = 0.01  # the optimiser's constraints are this much (normalised) tighter
    sample_updates: int = 3  # information on every 3rd update instant (0.48 s)
    maxiter: int = 200
    pan: bool = True  # design the pan; False keeps the arms deployed
    # The optimiser's variables are per harmonic k the amplitudes of the acceleration
    # (k w0)^2 a_dk in units of these (m/s^2, rad/s^2), and of the pan's rate k w0 a_dk (rad/s).
    acc_scale: tuple[float, ...] = (0.01, 0.01, 0.01, 0.01, 0.01, 0.01)
    pan_rate_scale_radps: float = 0.08
    spin: bool = True  # design secular (yaw, roll, pitch) rates too
    spin_scale_radps: float = 0.05


class ExcitationDesigner:
    """Optimises an ``ExcitationDesign`` for an ``ExcitationModel``."""

    def __init__(self, model: ExcitationModel, settings: DesignSettings | None = None) -> None:
        self.model = model
        self.s = settings or DesignSettings()
        s = self.s
        if s.n_harmonics < 1 or s.duration_s < 2 * s.ramp_s:
            raise ValueError("need n_harmonics >= 1 and duration_s >= 2 ramp_s")
        self.period_s = s.period_s or s.duration_s / 2
        # Limits on every update instant from t = 0; information on every
        # ``sample_updates``-th instant after the warm-up, weighted to stand for all.
        self.times, _, used = model.update_times(s.duration_s)
        self.used = used & (np.arange(self.times.size) % s.sample_updates == 0)
        self.weight = float(s.sample_updates)
        k_w = 2 * np.pi / self.period_s * np.tile(np.arange(1, s.n_harmonics + 1), 2)
        self._cache: dict = {}
        self._scale = np.vstack(
            (
                np.asarray(s.acc_scale, float)[:, None] / k_w**2,
                (s.pan_rate_scale_radps if s.pan else 0.0) / k_w[None, :],
            )
        )

    @property
    def n_vars(self) -> int:
        return self._scale.size + 3

    def free(self) -> np.ndarray:
        """1 for the variables being designed, 0 for those held at zero."""
        spin = np.full(3, 1.0 if self.s.spin else 0.0)
        return np.concatenate(((self._scale.ravel() > 0).astype(float), spin))

    def design_of(self, x: np.ndarray, info: dict | None = None) -> ExcitationDesign:
        """The design of the optimiser's variables x: the scaled Fourier coefficients, then the
        three spin rates."""
        x = np.asarray(x, float) * self.free()
        n = self._scale.size
        coeffs = x[:n].reshape(N_DOF, -1) * self._scale
        return ExcitationDesign(
            coeffs,
            self.period_s,
            self.s.duration_s,
            self.s.ramp_s,
            self.model.n_robots,
            info=info or {},
            spin_radps=tuple((x[n:] * self.s.spin_scale_radps).tolist()),
        )

    def evaluate(self, design: ExcitationDesign, times: np.ndarray | None = None) -> dict:
        """Bounds, the objective's terms and the worst violation of each constraint group."""
        traj = DesignedTrajectory(design)
        motion = traj.motion(self.times if times is None else times)
        cmd = self.model.commands(motion)
        viol = self.model.violations(motion, cmd)
        # The information on the estimator's instants (a grid from ``update_times``) only.
        used = self.used if times is None else np.ones(len(motion.t), dtype=bool)
        weight = self.weight if times is None else 1.0
        sub = Motion(*(getattr(motion, f.name)[used] for f in fields(Motion)))
        bounds = self.model.bounds(self.model.fisher(sub, weight, cmd[used]))
        return {
            "bounds": bounds,
            "ratios": self._ratios(bounds),
            "max_violation": {k: float(v.max()) for k, v in viol.items()},
            "viol": viol,
            "commands": cmd,
        }

    @staticmethod
    def _ratios(bounds: dict) -> np.ndarray:
        return np.array(
            [b / TARGETS["principal_rel"] for b in bounds["principal_rel"]]
            + [bounds["mass_rel"] / TARGETS["mass_rel"], bounds["com_m"] / TARGETS["com_m"]]
        )

    def objective_and_constraints(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """log(bound_i / target_i) (5,) and the constraints (>= 0 where satisfied): every
        sample's normalised values (robot and axis, wall axis, pan, pan rate) plus ``safety``,
        negated."""
        key = np.asarray(x, float).tobytes()
        if key in self._cache:
            return self._cache[key]
        ev = self.evaluate(self.design_of(x))
        cols = np.concatenate(list(ev["viol"].values()), axis=1)  # (N, C)
        # A little inside the limits, so that an iterate within SLSQP's tolerance, checked on
        # a finer grid, still holds them.
        out = (np.log(ev["ratios"]), -(cols.ravel() + self.s.safety))
        if len(self._cache) > 4 * self.n_vars:
            self._cache.clear()
        self._cache[key] = out
        return out

    def _jacobians(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward differences of ``objective_and_constraints``."""
        f0, c0 = self.objective_and_constraints(x)
        jf, jc = np.zeros((f0.size, x.size)), np.zeros((c0.size, x.size))
        free = self.free()
        for i in np.nonzero(free)[0]:
            xp = x.copy()
            xp[i] += self.s.fd_step
            f, c = self.objective_and_constraints(xp)
            jf[:, i] = (f - f0) / self.s.fd_step
            jc[:, i] = (c - c0) / self.s.fd_step
        return jf, jc

    def _solve(self, x0: np.ndarray) -> np.ndarray:
        """Minimax by SLSQP in epigraph form: minimise z subject to log ratio_i(x) <= z and the
        constraints, over v = (x, z)."""
        n = x0.size
        z0 = float(np.max(self.objective_and_constraints(x0)[0]))

        def cons(v):
            f, c = self.objective_and_constraints(v[:n])
            return np.concatenate((v[n] - f, c))

        def cons_jac(v):
            jf, jc = self._jacobians(v[:n])
            top = np.hstack((-jf, np.ones((jf.shape[0], 1))))
            return np.vstack((top, np.hstack((jc, np.zeros((jc.shape[0], 1))))))

        grad = np.zeros(n + 1)
        grad[n] = 1.0
        res = minimize(
            lambda v: v[n],
            np.append(x0, z0),
            jac=lambda v: grad,
            method="SLSQP",
            constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}],
            options={"maxiter": self.s.maxiter, "ftol": 1e-4},
        )
        self.last_result = res
        return res.x[:n] * self.free()

    def _feasible_scale(self, x: np.ndarray, step: float = 0.005) -> tuple[np.ndarray, float]:
        """x with every constraint satisfied on a 0.1 s grid: the pan's series scaled into its
        range and rate (both linear in it), then the cargo's motion by the largest c in 1,
        1 - step, ... that satisfies the rest. (A search from 1 down, not a bisection: the
        commands need not fall monotonically with c, since the attitude changes with it.)
        Returns x and c."""
        dense = np.arange(0.0, self.s.duration_s + 1e-9, 0.1)
        x = np.asarray(x, float).copy()
        pan = np.zeros(x.size, dtype=bool)
        n_per_dof = self._scale.shape[1]
        pan[PAN_DOF * n_per_dof : (PAN_DOF + 1) * n_per_dof] = True
        viol = self.evaluate(self.design_of(x), dense)["max_violation"]
        over = max(viol["pan"], viol["pan_rate"], 0.0)
        x[pan] *= (1.0 - 1e-9) / (1.0 + over)
        for c in np.arange(1.0, 0.0, -step):
            scaled = np.where(pan, x, c * x)
            ev = self.evaluate(self.design_of(scaled), dense)
            if max(ev["max_violation"].values()) <= 0:
                return scaled, float(c)
        return np.where(pan, x, 0.0), 0.0

    def run(self, verbose: bool = False) -> ExcitationDesign:
        s = self.s
        rng = np.random.default_rng(s.seed)
        free = self.free()
        start = time.perf_counter()
        best = None
        for k in range(s.starts):
            x0, _ = self._feasible_scale(rng.normal(0.0, s.start_std, self.n_vars) * free)
            x = self._solve(x0)
            x, shrink = self._feasible_scale(x)
            ev = self.evaluate(self.design_of(x))
            score = float(np.max(ev["ratios"]))
            if not np.isfinite(score):  # scaled to nothing: no information
                score = np.inf
            if verbose:
                print(
                    f"start {k}: worst bound/target {score:.3f} (shrink {shrink:.3f}), "
                    f"principal {np.round(100 * np.array(ev['bounds']['principal_rel']), 2)} %, "
                    f"mass {100 * ev['bounds']['mass_rel']:.2f} %, "
                    f"CoM {1e3 * ev['bounds']['com_m']:.2f} mm, "
                    f"{time.perf_counter() - start:.0f} s; SLSQP: {self.last_result.message} "
                    f"({self.last_result.nit} iterations)"
                )
            if best is None or score < best[0]:
                best = (score, x)
        runtime = time.perf_counter() - start
        design = self.design_of(best[1])
        return self.describe(design, runtime)

    def describe(
        self, design: ExcitationDesign, runtime_s: float | None = None
    ) -> ExcitationDesign:
        """The design with its predicted bounds, binding constraints and settings in ``info``."""
        dense = np.arange(0.0, design.duration_s + 1e-9, self.model.dt_s)
        ev = self.evaluate(design, dense)
        model = self.model
        traj = DesignedTrajectory(design)
        filtered = model.bounds(model.filtered_fisher(traj, design.duration_s))
        thrust = np.abs(ev["commands"]) / model.thrust_limit
        info = {
            "predicted_bounds": filtered,
            "predicted_bounds_unfiltered": self.evaluate(design)["bounds"],
            "targets": TARGETS,
            "max_violation": ev["max_violation"],
            "peak_thrust_ratio_per_axis": thrust.max(axis=(0, 1)).tolist(),
            "binding": sorted(ev["max_violation"], key=lambda k: -ev["max_violation"][k])[0],
            "limits": model.limits.__dict__,
            "settings": {k: v for k, v in self.s.__dict__.items()},
            "design_cargo_params_cargo_frame": model.cargo_params.tolist(),
            "runtime_s": runtime_s,
        }
        return ExcitationDesign(
            design.coeffs,
            design.period_s,
            design.duration_s,
            design.ramp_s,
            design.n_robots,
            design.center_m,
            info,
            design.spin_radps,
        )


# ------------------------------------------------------------------------------- from a World
def assembly_hull(world, pans_rad: np.ndarray) -> np.ndarray:
    """Corners (P, 3) of the collision boxes (MuJoCo's per-geom bounding boxes) of the cargo and
    every robot, in the cargo frame, for every robot's pan at each of ``pans_rad``: the hull the
    wall clearance is checked on. ``world``: an ``envs.world.World``."""
    import mujoco

    m = world.model
    data = world.make_data()
    geoms = [
        g
        for g in range(m.ngeom)
        if m.geom_bodyid[g] != 0 and (m.geom_contype[g] or m.geom_conaffinity[g])
    ]
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    points = []
    for pan in pans_rad:
        for h in world.robots:
            data.qpos[h.arm_qpos_adr[1]] = pan
        mujoco.mj_kinematics(m, data)
        rot_c = data.xmat[world.cargo_body].reshape(3, 3)
        pos_c = data.xpos[world.cargo_body]
        for g in geoms:
            center, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            local = center + signs * half
            world_pts = data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T
            points.append((world_pts - pos_c) @ rot_c)
    return np.concatenate(points)


def aisle_half_extents(world) -> np.ndarray:
    """Half extents (3,) of the free aisle, m: the inner faces of the module's wall slabs
    (``wall_*``, ``bulkhead_*``), moved in by the wall handrails (``rail_*``) on their wall."""
    m = world.model
    data = world.make_data()
    half = np.full(3, np.inf)
    rails = []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != 0:
            continue
        name = m.geom(g).name
        rot = data.geom_xmat[g].reshape(3, 3)
        c = data.geom_xpos[g] + rot @ m.geom_aabb[g, :3]
        h = np.abs(rot) @ m.geom_aabb[g, 3:]
        if name.startswith(("wall_", "bulkhead_")):
            a = int(np.argmin(h))
            half[a] = min(half[a], abs(c[a]) - h[a])
        elif name.startswith("rail_"):
            rails.append((c, h))
    for c, h in rails:
        gap = half - (np.abs(c) + h)  # the rail sits on the wall it is closest to
        a = int(np.argmin(gap))
        half[a] = min(half[a], abs(c[a]) - h[a])
    return half


def model_for_world(
    world,
    cargo_params: np.ndarray | None = None,
    estimator_kwargs: dict | None = None,
    dt_s: float = 1.0 / 62.5,
    limits: Limits | None = None,
) -> ExcitationModel:
    """An ``ExcitationModel`` of an ``envs.world.World``'s team, handrails, walls and hull.
    ``cargo_params`` (cargo frame): the design cargo; None: a 5 kg uniform bag, centre of mass
    at the bag's centre. ``estimator_kwargs``: the env's estimator settings (noise profile)."""
    import mujoco  # noqa: F401  (the World holds a compiled MuJoCo model)

    limits = limits or Limits()
    if cargo_params is None:
        cargo_params = params_from_mass_com_inertia(
            5.0, np.zeros(3), world.uniform_cargo_inertia(5.0)
        )
    rails = []
    m = world.model
    for site in world.handrail_sites:
        rot = quat_to_mat(np.asarray(m.site_quat[site], dtype=float))
        rails.append((rot, m.site_pos[site].copy()))
    pans = np.linspace(-limits.pan_range_rad, limits.pan_range_rad, 5)
    return ExcitationModel(
        [world.robot_model(i) for i in range(world.n_robots)],
        rails,
        cargo_params,
        dt_s,
        estimator_kwargs,
        assembly_hull(world, pans),
        aisle_half_extents(world),
        limits,
    )


# ------------------------------------------------------------------------------- for the env
EXCITE = "excite"
DESIGN_CACHE_DIR = Path.home() / ".cache" / "astrocargo" / "designs"


def is_trajectory_name(name: object) -> bool:
    """Whether ``name`` names a reference: one of ``Trajectory.NAMES``, "excite", or the path of
    a design JSON file (``*.json``)."""
    from .trajectories import Trajectory

    return isinstance(name, str) and (
        name in Trajectory.NAMES or name == EXCITE or name.endswith(".json")
    )


def trajectory_choices() -> str:
    """The accepted trajectory names, for error and help texts."""
    from .trajectories import Trajectory

    return f"one of {list(Trajectory.NAMES) + [EXCITE]} or the path of a design JSON file"


def load_design(path: str | Path, n_robots: int | None = None) -> ExcitationDesign:
    """The design in the JSON file ``path``, checked for ``n_robots`` if given; ``ValueError``
    naming the file if it is missing, unreadable, not a design, or for another team size."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"trajectory design file {str(path)!r} does not exist (or is not a file)")
    try:
        design = ExcitationDesign.from_dict(json.loads(path.read_text()))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"trajectory design file {str(path)!r} is not a design: {err}") from None
    except ValueError as err:
        raise ValueError(f"trajectory design file {str(path)!r}: {err}") from None
    if n_robots is not None and design.n_robots != n_robots:
        raise ValueError(f"{path} was designed for {design.n_robots} robots, not {n_robots}")
    return design


def check_trajectory(name: object, n_robots: int, fast: bool = False) -> None:
    """``ValueError`` unless ``name`` is a reference ``make_trajectory`` can build for a team of
    ``n_robots`` (a design file is read and checked here; "excite" without a shipped design is
    designed where the world is built)."""
    if not is_trajectory_name(name):
        raise ValueError(f"unknown trajectory {name!r}; allowed: {trajectory_choices()}")
    from .trajectories import Trajectory

    if name in Trajectory.NAMES:
        return
    if fast:
        raise ValueError("fast=True applies to the figure-eight trajectories, not to designs")
    if name != EXCITE:
        load_design(name, n_robots)


def has_design(n_robots: int) -> bool:
    """Whether a design for ``n_robots`` is shipped (``DESIGNS_DIR``)."""
    return (DESIGNS_DIR / f"excite_{int(n_robots)}robots.json").exists()


def make_trajectory(
    name: str,
    n_robots: int,
    fast: bool = False,
    world=None,
    estimator_kwargs: dict | None = None,
    settings: DesignSettings | None = None,
):
    """The reference a name stands for: ``Trajectory(name, fast)`` for the analytic ones; for
    "excite" the design shipped for ``n_robots`` (``shipped_design``), else one designed for
    ``world`` (an ``envs.world.World``: its team and bag) with ``estimator_kwargs`` and cached
    under ``DESIGN_CACHE_DIR``; for a path ending in ``.json`` that design (``load_design``).
    ``fast`` does not apply to designs (ValueError). A design on the fly that finds no flyable
    motion (every start scaled to rest) raises ``ValueError``."""
    from .trajectories import Trajectory

    check_trajectory(name, n_robots, fast)
    if name in Trajectory.NAMES:
        return Trajectory(name, fast=fast)
    if name != EXCITE:
        return DesignedTrajectory(load_design(name, n_robots))
    if has_design(n_robots) or world is None:
        return DesignedTrajectory(shipped_design(n_robots))
    noise_key = hashlib.sha1(
        json.dumps(estimator_kwargs or {}, sort_keys=True, default=str).encode()
    ).hexdigest()[:10]
    cached = DESIGN_CACHE_DIR / f"excite_{n_robots}robots_{world.cargo_bag.name}_{noise_key}.json"
    if cached.exists():
        return DesignedTrajectory(load_design(cached, n_robots))
    model = model_for_world(world, estimator_kwargs=estimator_kwargs)
    design = ExcitationDesigner(model, settings).run()
    if not np.any(design.coeffs) and not any(design.spin_radps):
        raise ValueError(
            f"the excitation designer found no flyable design for {n_robots} robots (every "
            f"start had to be scaled to rest to meet the limits; binding: "
            f"{design.info.get('binding')})"
        )
    design.save(cached)
    return DesignedTrajectory(design)
