"""What designs an excitation (``agents.excitation``: the design as data and as a trajectory):
the optimiser (``ExcitationDesigner``, ``DesignSettings``) on the model of
``agents.excitation_model`` (``ExcitationModel``, ``model_for_world``, ``Limits``; re-exported
here), which predicts a planned motion's commands and Fisher information with the project's own
estimator.

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

import numpy as np
from scipy.optimize import minimize

from .excitation import (
    N_DOF,
    PAN_DOF,
    TARGETS,
    DesignedTrajectory,
    ExcitationDesign,
    Motion,
    reference_motion,
)
from .excitation_model import (  # noqa: F401  (re-exported: the designer's public model)
    ExcitationModel,
    Limits,
    derived_jacobian,
    estimator_noise_terms,
    model_for_world,
)


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
