"""Excitation designed for information, as data and as a trajectory: a windowed finite Fourier
series of the cargo's motion and of the arms' pan (``ExcitationDesign``, its JSON file), the
reference it stands for (``DesignedTrajectory``, ``Motion``), the designs shipped with the
package and the names the env and scripts fly them by (``make_trajectory``,
``check_trajectory``, ``EXCITE``), and the room a design flies in (``aisle_half_extents``,
``assembly_hull``, from an ``envs.world.World``). What designs one (the Fisher information the
project's own estimator would get, the robots' limits, the optimiser) is in
``agents.excitation_design``.

Parameterisation (Swevers et al. 1997, a finite Fourier series per degree of freedom, here
windowed so that the motion starts and ends at rest): seven degrees of freedom d, the cargo
reference's position offset (x, y, z; m, module frame), its attitude as Z-X-Y angles
R = Rz(yaw) Rx(roll) Ry(pitch) (rad, as ``figure8_tumble``), and the pan angle of every robot's
arm (rad, one angle for the team: the controller and the env's reference carry one pan):

    q_d(t) = s(t) f_d(t),  f_d(t) = sum_k=1..K a_dk sin(k w0 t) + b_dk cos(k w0 t),  w0 = 2 pi / T0,

with s(t) the window rising from 0 to 1 over [0, T_r] and falling back over [T - T_r, T] (a
quintic smoothstep: s, s', s'' vanish at both ends), so q, q' and q'' are zero at t = 0 and
t = T: the cargo starts and ends at rest at the module centre, aligned, arms deployed.

Spins: besides the series, each attitude angle may carry a secular rate Omega_d windowed like
the series (angle += Omega_d S(t), S the window's integral): a spin that starts and ends at
rest (not at the start attitude).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .trajectories import Reference

if TYPE_CHECKING:
    from .excitation_design import DesignSettings

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


def reference_motion(reference, t: np.ndarray) -> Motion:
    """The ``Motion`` of any reference (a callable t -> ``Reference``, e.g. ``Trajectory``)
    on the time grid ``t`` (N,) s, so that a designer's model can score the analytic
    trajectories the same way as a design; the pan's acceleration by central differences
    (second order) of the pan rate."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    refs = [reference(float(x)) for x in t]

    def stack(name: str) -> np.ndarray:
        return np.array([getattr(r, name) for r in refs], dtype=float)

    pan_rate = stack("pan_rate")
    pan_acc = np.gradient(pan_rate, t) if t.size > 1 else np.zeros_like(pan_rate)
    return Motion(
        t, stack("pos"), stack("vel"), stack("acc"), stack("rot"), stack("w"), stack("wd"),
        stack("pan"), pan_rate, pan_acc,
    )  # fmt: skip


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

    def scaled(self, factor: float) -> ExcitationDesign:
        """The design with the cargo's motion (position and attitude series, spins) times
        ``factor`` in (0, 1] and the pan unchanged: headroom for the feedback (the commands fall
        roughly in proportion, the bounds rise roughly as 1 / factor). ``info`` records the
        factor (``"scaled"``, cumulative); its predictions are the unscaled design's until
        re-described (``ExcitationDesigner.describe``)."""
        if not 0 < factor <= 1:
            raise ValueError(f"factor must be in (0, 1], got {factor!r}")
        coeffs = self.coeffs.copy()
        coeffs[:PAN_DOF] *= factor
        info = {**self.info, "scaled": float(self.info.get("scaled", 1.0)) * factor}
        return ExcitationDesign(
            coeffs,
            self.period_s,
            self.duration_s,
            self.ramp_s,
            self.n_robots,
            self.center_m,
            info,
            tuple(factor * x for x in self.spin_radps),
        )

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
    ``traj(t)`` -> ``Reference``, ``arrays(t)`` (the env's packed form), ``motion(t)``
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

    def arrays(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference at ``t`` as ``Trajectory.arrays`` gives it: rotation (3, 3); pos, vel,
        acc, w, wd as the rows of a (5, 3), world axes; (pan, pan_rate) (2,)."""
        m = self.motion(np.array([float(t)]))
        vecs = np.stack((m.pos[0], m.vel[0], m.acc[0], m.w[0], m.wd[0]))
        return np.ascontiguousarray(m.rot[0]), vecs, np.array((m.pan[0], m.pan_rate[0]))

    def arrays_into(self, t: float, rot: np.ndarray, vecs: np.ndarray, pan: np.ndarray) -> None:
        """``arrays(t)`` written into ``rot``, ``vecs`` and ``pan`` (``Trajectory.arrays_into``)."""
        rot[:], vecs[:], pan[:] = self.arrays(t)

    def __call__(self, t: float) -> Reference:
        m = self.motion(np.array([float(t)]))
        return Reference(
            m.pos[0], m.vel[0], m.acc[0], m.rot[0], m.w[0], m.wd[0],
            float(m.pan[0]), float(m.pan_rate[0]),
        )  # fmt: skip


# ------------------------------------------------------------------------------- from a World
# The module's free aisle and the assembly's collision hull: the room a design flies in.
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
    from .excitation_design import ExcitationDesigner, model_for_world

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
