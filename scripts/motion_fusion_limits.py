"""How close fusing localization with the IMUs can bring the `nominal` bound to perfect sensors.

Flies one scenario (default: 2 robots, ``figure8_tumble``, 90 s, seed 0, the benchmark's cargo)
under ``nominal`` and under ``actuation_only`` (perfect sensors), keeps robot 0's recorded
measurements (z_k, A_k, b_k, R_k) and, per update, how the motion's sensor noise entered R_k, and
recomputes robot 0's Cramer-Rao bound with that noise modelled in time instead of per update.

The measurement of update k is z_k = A_k pi + b_k + e_k (``baselines``). Its motion part is
J_k xi_k: xi_k the filtered noise of every motion coordinate of the team (per robot: base
acceleration a_B (3), angular acceleration wd_B (3), joint accelerations qdd (2), base axes) and
J_k = N_k - K_k D_k the balance's map after the conditioning on the team's mismatch
(``motion.condition_maps``, recorded). The estimator enters it per update at its white-equivalent
level L (``motion.band_factors``): R_k = R_rest,k + J_k diag(L) J_k^T. Here the same noise enters
with its exact covariance over the run instead (Gaussian, all K updates at once):

    Sigma = blockdiag(R_rest,k) + J C J^T,   F = A^T Sigma^-1 A,   bound = ``baselines.crlb``'s
    derived quantities from F^-1,

C[k, l] the covariance of xi at updates k and l: per source c of one robot (two-sided PSD S_c(f),
white per sample of std s over the control period dt: S = s^2 dt),

    C_c(tau) = int S_c(f) (2 pi f)^(2 n_c) |H(f)|^2 cos(2 pi f tau) df,

n_c = 0, 1, 2 differentiations (accelerometer, gyro, encoders), H the estimator's chain (the 1 Hz
pre-filter and the slow filter, (w / (s + w))^3 each). The accelerometer's noise is white in world
axes too (a rotated white isotropic noise); between two updates its covariance in base axes is
R_BW(t_k) C(t_k - t_l) R_WB(t_l) (true base attitudes, the filters' short memory taken as one
attitude).

Localization: each robot's base position fix (std sigma_p per axis, every T s) is a second
measurement of its base's acceleration, with the PSD sigma_p^2 T (2 pi f)^4 once
differentiated twice. The best linear estimate of the base acceleration from both (the
non-causal Wiener / fixed-lag smoother: ``estimator.smoother``) has the error PSD

    S_fused(f) = S_a S_l(f) / (S_a + S_l(f)),   S_a = sigma_a^2 dt,   S_l = sigma_p^2 T (2 pi f)^4,

white above the crossover f_x = (S_a / (sigma_p^2 T))^(1/4) / (2 pi) and rising as f^4 below
it. Attitude: the gyro's angle random walk crosses the fixes' attitude noise at
f = sqrt(S_g / S_theta) / (2 pi), and the fixes cannot reach the angular acceleration (their PSD
(2 pi f)^4 S_theta against the gyro's (2 pi f)^2 S_g); both crossovers are printed.

The table's rows, each robot 0's 1-sigma bound on the principal moments over the perfect-sensor
one: "as recorded" (the benchmark's bound), "over time, the IMUs alone" (the same noise, its
covariance over the run), "accelerometers fused with localization" (their noise replaced by the
smoother's: the Wiener limit, then the fixed lags of ``--lags``), the same with noiseless gyros
(what any better attitude or angular-acceleration estimate could add) and "accelerometers
noiseless" (what no fusion of the accelerometers can beat). "GLS NEES" checks a model the
nominal data hold (the first two rows): generalised least squares on robot 0's data under it,
~10 when the model is true to them, far above when it is optimistic.

What the rows assume: the floors, the actuation and the peers' noise stay per update as the
benchmark models them (R_rest), also in the perfect-sensor bound; the conditioning's gain K_k is
the recorded one. The rows "over time" are bounds of an estimator that weighs the whole run's
balances with their correlated noise (generalised least squares, or a filter whose state carries
the noise's colour). The UKF, which treats updates as independent at the white-equivalent level,
keeps the "as recorded" bound whatever motion it is fed: the fused accelerometer's
white-equivalent level (its highest in the band, at the slow filter's cutoff) is the raw one.

Measured (5 seeds, 0..4; every seed within 0.01 of these): as recorded 1.26 / 1.37 / 1.21; over
time, the IMUs alone 1.16 / 1.31 / 1.12 (GLS NEES mean 13.5, as recorded 12.5; 95 % band of a
5-seed mean 6.5-14.3); accelerometers fused (Wiener) 1.13 / 1.22 / 1.11, by a fixed lag of 16 s
the same, of 8 s 1.14 / 1.25 / 1.11, of 4 s 1.16 / 1.29 / 1.12; gyros noiseless as well: no
change; accelerometers noiseless 1.02 / 1.01 / 1.02.

    .venv/bin/python scripts/motion_fusion_limits.py                 # seed 0
    .venv/bin/python scripts/motion_fusion_limits.py --seeds 0 1 2 3 4 --cache /tmp/flights
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmark_estimation as bench  # noqa: E402
import cli  # noqa: E402

from astrocargo.estimator.smoother import (  # noqa: E402
    crossover_hz,
    fused_psd_ratio,
    lagged_error_psd_ratio,
)

CONTROL_HZ = bench.CONTROL_HZ


def build_parser() -> argparse.ArgumentParser:
    parser = cli.limits_parser(__doc__, 2)
    parser.add_argument("--cache", type=Path, default=None, help="folder of recorded flights")
    parser.add_argument(
        "--lags", type=cli.positive_float, nargs="*", default=[4.0, 8.0, 16.0],
        help="s, fixed lags of the smoother to evaluate",
    )  # fmt: skip
    return parser


def fly(robots: int, trajectory: str, duration: float, seed: int, noise: str) -> dict:
    """One flight as the benchmark flies it; robot 0's recorded updates with, per update, the
    motion noise's conditioned map J (6, n), per-coordinate levels L (n,) and the true base
    attitudes R_WB of every robot (n_robots, 3, 3)."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(
        n_robots=robots, trajectory=trajectory, noise=noise,
        cargo_mass_kg=bench.CARGO_MASS, cargo_com_m=bench.CARGO_COM,
        cargo_inertia=bench.CARGO_INERTIA, max_cycles=int(round(duration * CONTROL_HZ)),
        estimator_kwargs={"record": True},
    )  # fmt: skip
    obs, _ = env.reset(seed=seed)
    sim = env.sim
    est = sim.estimators[0]
    taps = _tap_motion_noise(est)
    controller = ObservationController.for_env(env, "estimate")
    bases = [h.base_body for h in sim.world.robots]
    attitudes = []
    while env.agents:
        actions, _ = controller.predict(obs)
        obs, *_ = env.step(actions)
        attitudes.append(sim.data.xmat[bases].reshape(-1, 3, 3).copy())
    z, a, b, r = (np.stack(x) for x in zip(*est.log, strict=True))
    stamps = np.array([t[0] for t in taps.kept])
    out = {
        "z": z, "A": a, "b": b, "R": r, "stamps": stamps,
        "J": np.stack([t[1] for t in taps.kept]), "L": np.stack([t[2] for t in taps.kept]),
        # Control step k >= 1 (the reset's readings are stamp 0) is env.step number k.
        "R_wb": np.stack(attitudes)[stamps - 1],
        "truth": sim.true_params_grasp[0], "dt": sim.dt_s, "n_joints": sim.robots[0].n_joints,
        "update_every": est.update_every, "regressor_every": est.regressor_every,
        "cutoff_hz": est.cutoff_hz,
        # The pre-filter's delay is 3 / w with its -3 dB point at w sqrt(2^(1/3) - 1).
        "kinematics_cutoff_hz": 3.0 / est.pre.delay_s * np.sqrt(2 ** (1 / 3) - 1) / (2 * np.pi),
    }  # fmt: skip
    env.close()
    return out


class _LogTap(list):
    """``est.log`` that keeps, beside every appended update, the motion noise's pieces of the
    instant it was built from (rolled-back updates are deleted from both)."""

    def __init__(self, owner) -> None:
        super().__init__()
        self.owner = owner
        self.kept: list = []

    def append(self, item) -> None:
        super().append(item)
        self.kept.append(self.owner._smoother_last)

    def __delitem__(self, key) -> None:
        super().__delitem__(key)
        del self.kept[key]


def _tap_motion_noise(est) -> _LogTap:
    """Wrap ``est._motion_noise`` so that each instant's (stamp, J, L) is kept for the log."""
    from astrocargo.estimator.motion import pinv_symmetric
    from astrocargo.estimator.noise_model import _team_maps

    noise, inner = est.noise, est._motion_noise

    def motion_noise(inst, msgs):
        mean, cov = inner(inst, msgs)
        peers = [(est._relative[p].transform(), m) for p, m in zip(est.peers, msgs, strict=True)]
        params = est.ukf.params_mean()
        d_links, d_y = inst.motion_jac
        var, band, stacked, offsets = noise._stacked_motion(
            params, d_links, d_y, inst.regressor, peers
        )
        n_map, d_map, _ = _team_maps(params, d_links, d_y, inst.regressor, *stacked, offsets)
        level = var * band
        s_nd = (n_map * level) @ d_map.T
        s_dd = (d_map * level) @ d_map.T + noise.mismatch_model_var * np.eye(d_map.shape[0])
        jac = n_map - s_nd @ pinv_symmetric(s_dd) @ d_map
        est._smoother_last = (msgs[0].stamp, jac, level)
        return mean, cov

    est._motion_noise = motion_noise
    tap = _LogTap(est)
    est.log = tap
    return tap


def chain_power(freq_hz: np.ndarray, cutoffs_hz: tuple[float, ...]) -> np.ndarray:
    """|H(f)|^2 of the cascade of (w / (s + w))^3 filters with their -3 dB points at
    ``cutoffs_hz`` (``preprocess.StateVariableFilter``)."""
    w = 2 * np.pi * np.asarray(freq_hz, dtype=float)
    out = np.ones_like(w)
    for fc in cutoffs_hz:
        wc = 2 * np.pi * fc / np.sqrt(2 ** (1 / 3) - 1)
        out = out * (wc**2 / (wc**2 + w**2)) ** 3
    return out


def autocovariance(lags_s: np.ndarray, psd, cutoffs_hz, f_max_hz: float, df_hz: float):
    """C(tau) = int_-fmax^fmax psd(f) |H(f)|^2 cos(2 pi f tau) df (two-sided PSD) at ``lags_s``."""
    freq = np.arange(0.5, int(f_max_hz / df_hz)) * df_hz  # midpoints, f > 0
    weight = 2 * df_hz * psd(freq) * chain_power(freq, cutoffs_hz)
    return np.cos(2 * np.pi * np.outer(lags_s, freq)) @ weight


def crossovers(profile, dt_s: float) -> dict:
    """Where localization overtakes the IMU (Hz): position fixes against the accelerometer
    ((2 pi f)^4 sigma_p^2 T = sigma_a^2 dt) and attitude fixes against the gyro's angle
    ((2 pi f)^-2 sigma_g^2 dt = sigma_theta^2 T)."""
    t_fix = profile.localization_every * dt_s
    s_g, s_th = profile.gyro_std**2 * dt_s, profile.attitude_std_rad**2 * t_fix
    return {
        "accel_hz": crossover_hz(profile.accel_std, dt_s, profile.position_std_m, t_fix),
        "attitude_hz": np.sqrt(s_g / s_th) / (2 * np.pi),
    }


def principal_bound(fisher_rows: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Relative 1-sigma bound on the principal moments from whitened rows W A (M, 10):
    ``baselines.crlb`` on a recording of unit covariance whose Fisher information is
    (W A)^T (W A)."""
    from astrocargo.estimator.baselines import Recording, crlb
    from astrocargo.estimator.inertia import mass_com_inertia_from_params, principal_moments

    rows = fisher_rows.reshape(-1, 1, 10)
    k = rows.shape[0]
    rec = Recording(np.zeros((k, 1)), rows, np.zeros((k, 1)), np.ones((k, 1, 1)))
    moments = principal_moments(mass_com_inertia_from_params(truth)[2])
    return crlb(rec, truth)["std_principal"] / moments


def whitened(rec: dict, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """W A (6K, 10) and W (z - b) (6K,) with W^T W = Sigma^-1: ``cov`` the per-update
    covariances (K, 6, 6) (updates independent) or one over the run (6K, 6K)."""
    y = (rec["z"] - rec["b"])[..., None]
    if cov.ndim == 3:
        chol = np.linalg.cholesky(cov)
        return np.linalg.solve(chol, rec["A"]).reshape(-1, 10), np.linalg.solve(chol, y).ravel()
    chol = np.linalg.cholesky(0.5 * (cov + cov.T))
    k = rec["A"].shape[0]
    rows = np.linalg.solve(chol, np.hstack((rec["A"].reshape(6 * k, 10), y.reshape(6 * k, 1))))
    return rows[:, :10], rows[:, 10]


def full_covariance(rest: np.ndarray, motion_cov: np.ndarray) -> np.ndarray:
    """Sigma = blockdiag(rest) + motion_cov (6K, 6K)."""
    sigma = motion_cov.copy()
    for i in range(rest.shape[0]):
        sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += rest[i]
    return sigma


def recorded_bound(rec: dict, cov: np.ndarray | None = None) -> np.ndarray:
    """The benchmark's bound: updates independent, covariance ``cov`` (default the recorded R)."""
    rows, _ = whitened(rec, rec["R"] if cov is None else cov)
    return principal_bound(rows, rec["truth"])


def time_bound(rec: dict, rest: np.ndarray, motion_cov: np.ndarray) -> np.ndarray:
    """Bound with Sigma = blockdiag(rest) + motion_cov (6K, 6K): F = A^T Sigma^-1 A."""
    rows, _ = whitened(rec, full_covariance(rest, motion_cov))
    return principal_bound(rows, rec["truth"])


def gls_nees(rows: np.ndarray, resid: np.ndarray, truth: np.ndarray) -> float:
    """(pi - pi_true)^T F (pi - pi_true) of generalised least squares on whitened data
    (F = rows^T rows, pi = F^-1 rows^T resid): chi-square with 10 degrees of freedom when the
    covariance describes the data's noise (the check that a model is not optimistic)."""
    fisher = rows.T @ rows
    err = np.linalg.solve(fisher, rows.T @ resid) - truth
    return float(err @ fisher @ err)


ACCEL_MODELS = ("raw", "fused", "off")


def motion_covariance(rec: dict, profile, accel="raw", gyro: bool = True) -> np.ndarray:
    """J C J^T (6K, 6K) of the module docstring: every robot's accelerometer (``accel``: "raw",
    "fused" with its localization (the Wiener smoother), "off", or a function f -> its error
    PSD over the raw one, such as a fixed-lag smoother's), gyro (left out unless ``gyro``) and
    encoders over the run."""
    if not callable(accel) and accel not in ACCEL_MODELS:
        raise ValueError(f"accel must be one of {ACCEL_MODELS} or a function, got {accel!r}")
    dt = float(rec["dt"])
    stamps, jac, r_wb = rec["stamps"], rec["J"], rec["R_wb"]
    k, n_robots = len(stamps), r_wb.shape[1]
    per_robot = jac.shape[2] // n_robots
    lags = np.abs(stamps[:, None] - stamps[None, :]) * dt
    unique, inverse = np.unique(lags, return_inverse=True)
    cutoffs = (rec["kinematics_cutoff_hz"], rec["cutoff_hz"])
    f_x = crossovers(profile, dt)["accel_hz"]

    def cov_of(std, order, ratio=None):
        def psd(f):
            out = std**2 * dt * (2 * np.pi * f) ** (2 * order)
            return out if ratio is None else out * ratio(f)

        return autocovariance(unique, psd, cutoffs, 8.0, 2e-4)[inverse].reshape(k, k)

    fuse = (lambda f: fused_psd_ratio(f, f_x)) if accel == "fused" else None
    fuse = accel if callable(accel) else fuse
    sources = [(slice(6, per_robot), cov_of(profile.encoder_std_rad, 2), False)]
    if gyro:
        sources.append((slice(3, 6), cov_of(profile.gyro_std, 1), False))
    if accel != "off":
        sources.append((slice(0, 3), cov_of(profile.accel_std, 0, fuse), True))
    out = np.zeros((k, 6, k, 6))
    for r in range(n_robots):
        for cols, c_lag, rotate in sources:
            g = jac[:, :, r * per_robot + cols.start : r * per_robot + cols.stop]
            if rotate:  # base axes <- world axes at each update
                g = np.einsum("kia,kba->kib", g, r_wb[:, r])
            out += np.einsum("kl,kia,lja->kilj", c_lag, g, g)
    return out.reshape(6 * k, 6 * k)


def rest_covariance(rec: dict) -> np.ndarray:
    """R_k minus the motion noise the estimator put in per update, J diag(L) J^T (K, 6, 6)."""
    return rec["R"] - np.einsum("kia,ka,kja->kij", rec["J"], rec["L"], rec["J"])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return cli.parse_limits_args(build_parser(), argv, 2)


def _fly_cached(job: tuple[str, int, argparse.Namespace]) -> tuple[str, int, dict]:
    noise, seed, args = job
    path = None
    if args.cache is not None:
        name = f"{args.trajectory}_{args.robots}r_{args.duration:g}s_{noise}_{seed}.npz"
        path = args.cache / name
        if path.exists():
            return noise, seed, dict(np.load(path))
    rec = fly(args.robots, args.trajectory, args.duration, seed, noise)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **rec)
    return noise, seed, rec


def lagged_ratio(lag_s: float, dt_s: float, profile):
    """f -> the fixed-lag smoother's error PSD over the accelerometer's at a lag of ``lag_s``
    (``smoother.lagged_error_psd_ratio`` on a log grid to 2 Hz, interpolated in log f; 1 above,
    where it is 1 within 1e-3 at any lag)."""
    grid = np.geomspace(1e-4, 2.0, 120)
    ratio = lagged_error_psd_ratio(
        grid, int(round(lag_s / dt_s)), dt_s, profile.accel_std, profile.position_std_m,
        profile.localization_every,
    )  # fmt: skip
    return lambda f: np.interp(np.log(f), np.log(grid), ratio, left=ratio[0], right=1.0)


def bounds(nominal: dict, perfect: dict, profile, lags: dict) -> dict[str, tuple]:
    """Per model (the rows of ``main``'s table): robot 0's principal-moment bound over the
    perfect-sensor one, and generalised least squares' NEES on the nominal flight's data under
    that model (None where the model is not the data's: fused or noiseless sensors). ``lags``:
    {lag s: ``lagged_ratio``}, a row each."""
    base = recorded_bound(perfect)
    rest = rest_covariance(nominal)
    rows, resid = whitened(nominal, nominal["R"])
    out = {
        "as recorded (the benchmark)": (
            principal_bound(rows, nominal["truth"]) / base,
            gls_nees(rows, resid, nominal["truth"]),
        )
    }
    models = [
        ("over time, the IMUs alone", "raw", True),
        ("over time, accelerometers fused with localization", "fused", True),
        *((f"over time, fused by a {lag:g} s fixed lag", lags[lag], True) for lag in lags),
        ("over time, accelerometers fused, gyros noiseless", "fused", False),
        ("over time, accelerometers noiseless", "off", True),
    ]
    for label, accel, gyro in models:
        rows, resid = whitened(nominal, full_covariance(rest, motion_covariance(
            nominal, profile, accel, gyro)))  # fmt: skip
        # The data hold the raw IMUs' noise: only their model can be checked on them.
        nees = gls_nees(rows, resid, nominal["truth"]) if label == models[0][0] else None
        out[label] = (principal_bound(rows, nominal["truth"]) / base, nees)
    return out


def main(argv: list[str] | None = None) -> None:
    from astrocargo.envs.sensors import NOISE_PROFILES

    args = parse_args(argv)
    profile = NOISE_PROFILES["nominal"]
    jobs = [(noise, seed, args) for seed in args.seeds for noise in ("nominal", "actuation_only")]
    with ProcessPoolExecutor(args.workers) as pool:
        flights = {(noise, seed): rec for noise, seed, rec in pool.map(_fly_cached, jobs)}
    dt = float(flights[jobs[0][:2]]["dt"])
    lags = {lag: lagged_ratio(lag, dt, profile) for lag in args.lags}
    cross = crossovers(profile, dt)
    cutoff = float(flights[jobs[0][:2]]["cutoff_hz"])
    print(
        f"{args.robots} robots, {args.trajectory}, {args.duration:g} s: robot 0's Cramer-Rao "
        "bound on the principal moments (I1 / I2 / I3) over the perfect-sensor bound"
    )
    print(
        f"localization overtakes the accelerometer below {cross['accel_hz']:.3f} Hz; the "
        f"attitude fixes overtake the integrated gyro below {cross['attitude_hz']:.4f} Hz; the "
        f"fused accelerometer's white-equivalent level at the band's edge ({cutoff:g} Hz) is "
        f"{fused_psd_ratio(cutoff, cross['accel_hz']):.4f} of the raw one"
    )
    print("| seed | model of the motion noise | / perfect sensors | within 1.3x | GLS NEES |")
    print("|---|---|---|---|---|")
    for seed in args.seeds:
        rows = bounds(flights[("nominal", seed)], flights[("actuation_only", seed)], profile, lags)
        for label, (ratio, nees) in rows.items():
            cells = " / ".join(f"{x:.2f}" for x in ratio)
            within = "yes" if ratio.max() <= 1.3 else "no"
            check = "-" if nees is None else f"{nees:.1f}"
            print(f"| {seed} | {label} | {cells} | {within} | {check} |")
    print("(GLS NEES: generalised least squares on the nominal data under the row's model, ~10 "
          "for a model true to the data; one draw per seed)")  # fmt: skip


if __name__ == "__main__":
    main()
