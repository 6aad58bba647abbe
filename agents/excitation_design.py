"""What designs an excitation (``agents.excitation``: the design as data and as a trajectory):
the model of the team, the design cargo and the project's own estimator that predicts a planned
motion's commands and Fisher information (``ExcitationModel``, ``model_for_world``), the limits
it must respect (``Limits``) and the optimiser (``ExcitationDesigner``, ``DesignSettings``).

What the estimator sees (``estimator.cargo_estimator``): per update instant k (every
``update_every`` control steps after ``warmup_s``) the wrench balance in robot 0's grasp frame G,
z_k = A_k pi + b_k + e_k, with A_k = ``rne.body_regressor`` of G's motion (G is fixed to the
cargo: its acceleration, angular velocity and acceleration follow from the cargo's) and e_k of
covariance R_k = meas_cov + (sum_j M_j diag(s_j^2) M_j^T) / update_every + motion_cov, where
s_j = abs + rel |u_j| is robot j's actuation noise per axis at its command u_j, M_j carries it
into G (``grasp_from_base`` of the thrust site; peers through the known relative grasp) and
motion_cov is the sensors' noise on the filtered motion as the estimator models it
(``estimator.motion``, ``motion_fusion``: every robot's E Sigma E^T, conditioned on the peers'
grasp-acceleration mismatches), at the design cargo. It depends on the joint angles only, so it
is tabulated over the pan like the team's geometry (``estimator_noise_terms``). The Fisher
information F = sum_k A_k^T R_k^-1 A_k and the Cramer-Rao bounds of mass, centre of mass and
principal moments (``baselines.derived_covariance``) are what ``scripts/benchmark_estimation.py``
computes from a flight's recording.

Commands u_j: the robots and the cargo move as one rigid body (the pan is slow); the wrench the
planned motion needs about the composite centre of mass, M (a + wd x r + w x (w x r)) and
I_c wd + w x I_c w (cargo axes), is shared by ``CooperativeController``'s allocation (minimum norm
weighted by each robot's limits) on the design cargo, at the planned pan.

Objective: the worst of log(bound_i / target_i) over the three principal moments (relative),
the mass (relative) and the centre of mass (norm of the per-axis bounds, m); the targets are
the issue's (``TARGETS``) or a reference trajectory's own bounds (``DesignSettings.targets``,
``reference_bounds``: then the worst improvement over it is maximised); minimised in
epigraph form (minimise z subject to log(bound_i / target_i) <= z), a minimax. Constraints, at
every sample of a time grid: every robot's command per axis within (1 - ``thrust_margin``) of
its limit (the rest is left to the feedback), every point of the assembly's collision hull
``clearance_m`` inside the aisle's walls, pan within its range and its rate within
``pan_rate_margin`` of the servo's 0.12 rad/s. Solved by SLSQP (scipy) with forward-difference
Jacobians from several random starts, each first scaled down until it is feasible; the best
design is scaled down, if need be, until every constraint holds on a 0.1 s grid.

"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from types import SimpleNamespace

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
from astrocargo.estimator.motion import grasp_acc_map
from astrocargo.estimator.rne import (
    RobotDescription,
    balance_motion_jacobians,
    body_regressor,
    grasp_from_base,
    grasp_pose,
    link_poses,
    wrench_transform,
)

from .excitation import (
    N_DOF,
    PAN_DOF,
    PAN_RANGE_RAD,
    SERVO_RATE_RADPS,
    TARGETS,
    TILT_DEPLOYED_RAD,
    DesignedTrajectory,
    ExcitationDesign,
    Motion,
    aisle_half_extents,
    assembly_hull,
    reference_motion,
)


# ------------------------------------------------------------------------------- ESTIMATOR COUPLING
# The ONE place that reads CargoEstimator's noise model: its public NoiseModel
# (``estimator.noise``: ``motion_noise``, the per-instant covariance the estimator's updates use),
# meas_cov, the actuation noise and update_every. Nothing else in this module depends on how R is
# built.
def estimator_noise_terms(
    estimator: CargoEstimator,
    robots: list[RobotDescription],
    relative_grasps: dict[int, tuple[np.ndarray, np.ndarray]],
    cargo_grasp: np.ndarray,
    joint_angles: np.ndarray,
) -> dict:
    """The parts of the estimator's per-update measurement covariance (``CargoEstimator.process``)

        R = meas_cov + (sum_j M_j diag(s_j^2) M_j^T) / update_every + motion_cov,

    s_j = actuation_abs + actuation_rel |u_j| per axis of robot j's command u_j [N; N m],
    M_j its thrust site -> robot 0's grasp frame G (assembled by the caller), at one team
    configuration: every robot at ``joint_angles`` (n_joints,) rad, peers' grasps
    ``relative_grasps`` {j: (rotation, position m)} in G, the cargo ``cargo_grasp`` (10,) (G) as
    the estimate. ``motion_cov`` (6, 6) is ``NoiseModel.motion_noise``'s covariance (the
    sensors' noise on the filtered motion, conditioned on the peers' grasp-acceleration
    mismatches for ``motion_fusion="team"``; it does not depend on the observed mismatch, so
    the peers' messages carry zero accelerations here). The Jacobians are exact and depend on
    the joint angles only (the balance is affine in xi = (a_B, wd_B, qdd) with coefficients free
    of the angular and joint rates), so this is the estimator's covariance at every instant of
    that configuration.

    Returns {"meas_cov", "motion_cov": (6, 6); "actuation_abs", "actuation_rel": (6,);
    "update_every": int}."""
    est = estimator
    q = np.asarray(joint_angles, dtype=float)
    zero3, zero_q = np.zeros(3), np.zeros(q.size)
    params = np.asarray(cargo_grasp, dtype=float)

    def jacobians(robot):
        return balance_motion_jacobians(robot, zero3, zero3, zero3, q, zero_q, zero_q)

    spec = est.noise.motion
    peers = []
    for j, (rot, pos) in sorted(relative_grasps.items()):
        links_j, y_j = jacobians(robots[j])
        message = SimpleNamespace(
            grasp_acc=np.zeros(3),
            motion_links_jac=links_j,
            motion_grasp_jac=grasp_acc_map(y_j),
            motion_var=spec.var,
            motion_band=spec.band,
        )
        peers.append((wrench_transform(rot, pos), message))
    lever = float(np.linalg.norm(grasp_pose(robots[0], q)[1]))
    motion_cov = est.noise.motion_noise(
        est.motion_fusion, params, jacobians(robots[0]), np.zeros((6, 10)), peers, lever
    )[1]
    return {
        "meas_cov": est.meas_cov.copy(),
        "motion_cov": motion_cov,
        "actuation_abs": est._actuation_abs.copy(),
        "actuation_rel": est._actuation_rel.copy(),
        "update_every": int(est.update_every),
    }


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
        self.relative_grasps = relative
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
        # The estimator's noise at this configuration (a function of the joint angles only).
        terms = estimator_noise_terms(
            self.estimator,
            self.robots,
            self.relative_grasps,
            self.cargo_grasp,
            np.array([TILT_DEPLOYED_RAD, pan]),
        )
        self._noise_terms = terms
        return {
            "mass": mass,
            "com": com,
            "inertia": inertia,
            "alloc": alloc,
            "noise": np.stack(noise_maps),
            "motion_cov": terms["motion_cov"],
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
        """R (N, 6, 6) of the estimator's update at each sample (``estimator_noise_terms``):
        meas_cov + (sum_j M_j diag(s_j^2) M_j^T) / update_every + motion_cov at the planned pan
        (the motion covariance interpolated linearly between the tabulated pans, a convex
        combination of covariances), ``commands`` (N, n_robots, 6)."""
        team = self.team(motion.pan)
        terms = self._noise_terms
        std = terms["actuation_abs"] + terms["actuation_rel"] * np.abs(commands)  # (N, n, 6)
        act = np.einsum("nkij,nkj,nklj->nil", team["noise"], std**2, team["noise"])
        return terms["meas_cov"] + act / terms["update_every"] + team["motion_cov"]

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
        filt = est.balance_layout_filter()
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
    # What the bounds are scored against: {"principal_rel": scalar or 3 (ascending moments),
    # "mass_rel", "com_m"}; None: the TARGETS. The bounds a reference trajectory gets
    # (``ExcitationDesigner.reference_bounds``) make the objective the worst improvement over
    # that trajectory.
    targets: dict | None = None


class ExcitationDesigner:
    """Optimises an ``ExcitationDesign`` for an ``ExcitationModel``."""

    def __init__(self, model: ExcitationModel, settings: DesignSettings | None = None) -> None:
        self.model = model
        self.s = settings or DesignSettings()
        s = self.s
        if s.n_harmonics < 1 or s.duration_s < 2 * s.ramp_s:
            raise ValueError("need n_harmonics >= 1 and duration_s >= 2 ramp_s")
        self.period_s = s.period_s or s.duration_s / 2
        targets = TARGETS if s.targets is None else s.targets
        self.targets = np.concatenate(
            (
                np.broadcast_to(np.asarray(targets["principal_rel"], float), (3,)),
                [float(targets["mass_rel"]), float(targets["com_m"])],
            )
        )
        if not np.all(self.targets > 0):
            raise ValueError(f"targets must be positive, got {targets}")
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

    def _ratios(self, bounds: dict) -> np.ndarray:
        """bound / target: the three principal moments (ascending), mass, centre of mass."""
        values = list(bounds["principal_rel"]) + [bounds["mass_rel"], bounds["com_m"]]
        return np.array(values) / self.targets

    def reference_bounds(self, reference) -> dict:
        """The bounds (``ExcitationModel.bounds``) a reference trajectory (t -> ``Reference``,
        e.g. ``Trajectory("figure8_tumble")``) gets on the designer's own grid of update
        instants, as a design is scored: usable as ``DesignSettings.targets``."""
        motion = reference_motion(reference, self.times[self.used])
        return self.model.bounds(self.model.fisher(motion, self.weight))

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
            "targets": {
                "principal_rel": self.targets[:3].tolist(),
                "mass_rel": float(self.targets[3]),
                "com_m": float(self.targets[4]),
            },
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
