"""The model an excitation is designed on (``agents.excitation_design`` optimises on it): the
team, the design cargo and the project's own estimator that predict a planned motion's commands
and Fisher information (``ExcitationModel``, ``model_for_world``), and the limits it must
respect (``Limits``).

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
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
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
    PAN_RANGE_RAD,
    SERVO_RATE_RADPS,
    TILT_DEPLOYED_RAD,
    DesignedTrajectory,
    Motion,
    aisle_half_extents,
    assembly_hull,
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
