"""How close the IMU's noise weighed over time, and localization, bring the bound to the ideal.

Flies one scenario (default: 2 robots, ``figure8_tumble``, 90 s, seed 0, the benchmark's cargo)
three times: under ``nominal`` with the estimators' ``over_time_window`` 0 (each update alone,
the IMU's channels at the lag-weighted covariance W: the benchmark's bound before the window)
and L (``--window``: each update conditioned on the last L used ones, ``estimator.over_time``),
and under ``actuation_only`` (perfect sensors). From robot 0 it keeps what its filter recorded
(z_k, A_k, b_k, R_k) and, with the window, every used update's own measurement before the
conditioning with its team IMU map J_k (6, c, 4) (``NoiseModel.over_time_noise``: the
conditioned map of the c = 6 per robot IMU channels' modes, 4 per channel), and recomputes
robot 0's Cramer-Rao bound (``baselines.crlb``'s derived quantities) under these models of the
measurement noise:

- each update alone, as recorded with window 0 and with window L (white across updates: the
  filter's own bound);
- over the whole run (generalised least squares on all K used updates at once): the
  covariance Sigma (6K, 6K) with the updates' own R_k on the diagonal and
  J_k,c Gm_c(l - k) J_l,c^T between updates, Gm the modes' covariance L updates apart
  (``over_time.mode_lag_covariances``, from the estimator's own chain kernels, the momentum
  chain of ``noise_model``); the floors, the actuation, the peers' channel noise, the encoders
  (errors in variables) and the squared rates stay white per update, as in the estimator;
- the accelerometers fused with localization: their modes' Gm for the input PSD of the best
  linear estimate of each base's acceleration from both (the non-causal Wiener smoother, and
  the fixed lags of ``--lags``, ``estimator.smoother``),

      S_fused(f) = S_a S_l(f) / (S_a + S_l(f)),  S_a = sigma_a^2 dt,  S_l = sigma_p^2 T (2 pi f)^4,

  white above the crossover f_x = (S_a / (sigma_p^2 T))^(1/4) / (2 pi) and rising as f^4 below
  it; Gm(L) = F^+ G(L) F^+T with G(L)[a, b] = sum_m K_a[m] K_b[m + L u] taken through the
  kernels' FFT with that spectrum (checked against the direct sums for a white input), F the
  estimator's modes (its white G(0)'s factor); their part of each diagonal block J Gm(0) J^T;
- with noiseless gyros as well, and with noiseless accelerometers.

"GLS NEES" checks a model the nominal data hold (the first three rows): generalised least
squares on robot 0's data under it, ~10 when the model is true to them, far above when it is
optimistic. Localization's crossovers with the accelerometer and the integrated gyro are
printed: the attitude fixes cannot reach the angular acceleration.

Measured (5 seeds, 0..4; ranges over the seeds, docs/estimation_limits.md): window 0
1.24 / 1.35-1.36 / 1.19-1.20 (GLS NEES mean 13.4); window 24 and the whole run alike
1.34-1.35 / 1.40 / 1.29-1.30 (14.4; 95 % band of a 5-seed mean 6.5-14.3); accelerometers fused
(Wiener, and a 16 s lag) 1.30 / 1.27-1.28 / 1.27, an 8 s lag 1.32 / 1.32-1.33 / 1.28-1.29, 4 s
1.34 / 1.38 / 1.29-1.30; gyros noiseless as well: no change; accelerometers noiseless
1.01 / 1.01 / 1.01-1.02.

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

from astrocargo.estimator.cargo_estimator import CargoEstimator  # noqa: E402
from astrocargo.estimator.fused_motion import (  # noqa: E402
    coloured_lag_covariances,
    fused_error_ratio,
)
from astrocargo.estimator.motion import HELD_EXTENDED, kernel_lag_covariances  # noqa: E402
from astrocargo.estimator.noise_model import NoiseModel, momentum_chain_kernels  # noqa: E402
from astrocargo.estimator.over_time import DEFAULT_WINDOW, cross_covariance  # noqa: E402
from astrocargo.estimator.smoother import (  # noqa: E402
    crossover_hz,
    fused_psd_ratio,
)

CONTROL_HZ = bench.CONTROL_HZ


def build_parser() -> argparse.ArgumentParser:
    parser = cli.limits_parser(__doc__, 2)
    parser.add_argument("--cache", type=Path, default=None, help="folder of recorded flights")
    parser.add_argument(
        "--lags", type=cli.positive_float, nargs="*", default=[4.0, 8.0, 16.0],
        help="s, fixed lags of the smoother to evaluate",
    )  # fmt: skip
    parser.add_argument(
        "--window", type=cli.positive_int, default=DEFAULT_WINDOW,
        help="updates, the estimator's over_time_window of the conditioned flight",
    )  # fmt: skip
    return parser


def fly(robots: int, trajectory: str, duration: float, seed: int, noise: str, window: int) -> dict:
    """One flight as the benchmark flies it, the estimators' ``over_time_window`` = ``window``:
    robot 0's recorded updates (z, A, b, R: what its filter measured) and, with a window, every
    used update's own measurement before the conditioning (raw_*), its update count and its
    team IMU map J (6, c, 4) (``over_time.UpdateWindow``'s entries)."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(
        n_robots=robots, trajectory=trajectory, noise=noise,
        cargo_mass_kg=bench.CARGO_MASS, cargo_com_m=bench.CARGO_COM,
        cargo_inertia=bench.CARGO_INERTIA, max_cycles=int(round(duration * CONTROL_HZ)),
        estimator_kwargs={"record": True, "over_time_window": window},
    )  # fmt: skip
    obs, _ = env.reset(seed=seed)
    sim = env.sim
    est = sim.estimators[0]
    entries = _tap_window(est) if window else []
    controller = ObservationController.for_env(env, "estimate")
    while env.agents:
        actions, _ = controller.predict(obs)
        obs, *_ = env.step(actions)
    z, a, b, r = (np.stack(x) for x in zip(*est.log, strict=True))
    out = {"z": z, "A": a, "b": b, "R": r, "truth": sim.true_params_grasp[0]}
    if entries:
        out.update(
            raw_z=np.stack([e.z for e in entries]), raw_A=np.stack([e.regressor for e in entries]),
            raw_b=np.stack([e.offset for e in entries]), raw_R=np.stack([e.cov for e in entries]),
            index=np.array([e.index for e in entries]),
            J=np.stack([e.imu_map for e in entries]),
        )  # fmt: skip
    env.close()
    return out


def _tap_window(est) -> list:
    """The used updates' window entries, in order (rolled-back ones removed): ``est._window``'s
    ``add`` and ``drop_from`` wrapped."""
    window, kept = est._window, []
    add, drop_from = window.add, window.drop_from

    def tapped_add(entry) -> None:
        if entry is None:
            raise RuntimeError("an update without the team's IMU map: not a full-run model")
        add(entry)
        kept.append(entry)

    def tapped_drop(stamp: int) -> None:
        drop_from(stamp)
        kept[:] = [e for e in kept if e.stamp < stamp]

    window.add, window.drop_from = tapped_add, tapped_drop
    return kept


def chain_model(robots: int) -> NoiseModel:
    """The default estimator's noise model with ``over_time`` on (its kernels and modes)."""
    from astrocargo.envs.world import World

    world = World(robots)
    est = CargoEstimator(world.robot_model(0), 0, tuple(range(1, robots)), 1.0 / CONTROL_HZ,
                         over_time_window=DEFAULT_WINDOW)  # fmt: skip
    return est.noise


def mode_lags(model: NoiseModel, ratio=None) -> np.ndarray:
    """Gm (n_lags + 1, 4, 4) of a held channel's modes (``over_time.mode_lag_covariances``) for
    an input whose PSD is the white one's times ``ratio(f)`` (None: white): the kernels' lag
    covariances G(L)[a, b] = sum_m K_a[m] K_b[m + L u], through the FFT with the input's
    spectrum, in the white modes F^+ (what the estimator's maps J carry)."""
    kernels = momentum_chain_kernels(*model.chain_args)[0][HELD_EXTENDED]
    dt, n_lags = model.chain_args[0], model.mode_lag_cov.shape[0] - 1
    cross = coloured_lag_covariances(kernels, dt, model.update_every, n_lags, ratio)
    white = kernel_lag_covariances(kernels, model.update_every, n_lags)
    if ratio is None and not np.allclose(cross, white, atol=1e-12):
        raise AssertionError("the FFT's lag covariances differ from the kernels'")
    s, u = np.linalg.eigh(white[0])
    inv = (u / np.sqrt(s)).T
    return inv @ cross @ inv.T


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


def gls_nees(rows: np.ndarray, resid: np.ndarray, truth: np.ndarray) -> float:
    """(pi - pi_true)^T F (pi - pi_true) of generalised least squares on whitened data
    (F = rows^T rows, pi = F^-1 rows^T resid): chi-square with 10 degrees of freedom when the
    covariance describes the data's noise (the check that a model is not optimistic)."""
    fisher = rows.T @ rows
    err = np.linalg.solve(fisher, rows.T @ resid) - truth
    return float(err @ fisher @ err)


def run_covariance(rec: dict, gyro_lags, accel_lags) -> np.ndarray:
    """Sigma (6K, 6K) of the K used updates' own measurements over the whole run: R_k on the
    diagonal, with the accelerometers' part J_a J_a^T replaced by J_a Gm_acc(0) J_a^T, and
    J_k,c Gm_c(l - k) J_l,c^T between updates (``over_time``) per channel kind c (gyro,
    accelerometer; ``gyro_lags``, ``accel_lags`` a kind's Gm, None: that kind noiseless)."""
    jac, index, cov = rec["J"], rec["index"], rec["raw_R"]
    k, n_ch = jac.shape[0], jac.shape[2]
    kinds = [(np.flatnonzero(np.arange(n_ch) % 6 < 3), gyro_lags),
             (np.flatnonzero(np.arange(n_ch) % 6 >= 3), accel_lags)]  # fmt: skip
    n_lags = max(g.shape[0] for _, g in kinds if g is not None) - 1
    sigma = np.zeros((6 * k, 6 * k))
    for i in range(k):
        block = cov[i].copy()
        for cols, lags in kinds:
            j = np.ascontiguousarray(jac[i][:, cols])
            block -= cross_covariance(j, j, np.eye(4))
            if lags is not None:
                block += cross_covariance(j, j, lags[0])
        sigma[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = block
        for m in range(i + 1, k):
            lag = index[m] - index[i]
            if lag > n_lags:
                break
            cross = np.zeros((6, 6))
            for cols, lags in kinds:
                if lags is not None:
                    a, b = (np.ascontiguousarray(jac[x][:, cols]) for x in (i, m))
                    cross += cross_covariance(a, b, lags[lag])
            sigma[6 * i : 6 * i + 6, 6 * m : 6 * m + 6] = cross
            sigma[6 * m : 6 * m + 6, 6 * i : 6 * i + 6] = cross.T
    return sigma


def raw(rec: dict) -> dict:
    """The used updates' own measurements (before the conditioning) as a record."""
    return {"z": rec["raw_z"], "A": rec["raw_A"], "b": rec["raw_b"], "truth": rec["truth"]}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return cli.parse_limits_args(build_parser(), argv, 2)


def _fly_cached(job: tuple[str, int, int, argparse.Namespace]) -> tuple[tuple, dict]:
    noise, seed, window, args = job
    path = None
    if args.cache is not None:
        name = f"{args.trajectory}_{args.robots}r_{args.duration:g}s_{noise}_{seed}_w{window}.npz"
        path = args.cache / name
        if path.exists():
            return (noise, seed, window), dict(np.load(path))
    rec = fly(args.robots, args.trajectory, args.duration, seed, noise, window)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **rec)
    return (noise, seed, window), rec


def lagged_ratio(lag_s: float, dt_s: float, profile):
    """f -> the fixed-lag smoother's error PSD over the accelerometer's at a lag of ``lag_s``
    (``fused_motion.fused_error_ratio``: the estimator's own, the fixes' attitude error left
    out here as in the bound's model)."""
    return fused_error_ratio(
        int(round(lag_s / dt_s)), dt_s, profile.accel_std, profile.position_std_m,
        profile.localization_every,
    )  # fmt: skip


def bounds(per_update: dict, windowed: dict, perfect: dict, lags: dict) -> dict[str, tuple]:
    """Per model (the rows of ``main``'s table): robot 0's principal-moment bound over the
    perfect-sensor one, and generalised least squares' NEES on the nominal data under that model
    (None where the model is not the data's: fused or noiseless sensors). ``per_update``,
    ``windowed``: the nominal flights with ``over_time_window`` 0 and L; ``lags``: {row label:
    the accelerometers' Gm}, with "raw" the white one."""
    rows, _ = whitened(perfect, perfect["R"])
    base = principal_bound(rows, perfect["truth"])
    out = {}
    for label, rec in (
        ("each update alone, IMU at the lag-weighted W (window 0, the benchmark's before)",
         per_update),
        ("each update conditioned on the window (what the filter records)", windowed),
    ):  # fmt: skip
        rows, resid = whitened(rec, rec["R"])
        nees = gls_nees(rows, resid, rec["truth"])
        out[label] = (principal_bound(rows, rec["truth"]) / base, nees)
    data, white = raw(windowed), lags["raw"]
    models = [
        ("over the whole run, the IMUs alone", white, white),
        *((f"over the run, accelerometers {k}", white, g) for k, g in lags.items() if k != "raw"),
        ("over the run, accelerometers fused (Wiener), gyros noiseless", None, lags["fused"]),
        ("over the run, accelerometers noiseless", white, None),
    ]
    for label, gyro, accel in models:
        rows, resid = whitened(data, run_covariance(windowed, gyro, accel))
        # The data hold the raw IMUs' noise: only their model can be checked on them.
        nees = gls_nees(rows, resid, data["truth"]) if label == models[0][0] else None
        out[label] = (principal_bound(rows, data["truth"]) / base, nees)
    return out


def main(argv: list[str] | None = None) -> None:
    from astrocargo.envs.sensors import NOISE_PROFILES

    args = parse_args(argv)
    profile = NOISE_PROFILES["nominal"]
    cases = [("nominal", 0), ("nominal", args.window), ("actuation_only", 0)]
    jobs = [(noise, seed, w, args) for seed in args.seeds for noise, w in cases]
    with ProcessPoolExecutor(args.workers) as pool:
        flights = dict(pool.map(_fly_cached, jobs))
    dt = 1.0 / CONTROL_HZ
    model = chain_model(args.robots)
    cross = crossovers(profile, dt)
    lags = {
        "raw": mode_lags(model),
        "fused": mode_lags(model, lambda f: fused_psd_ratio(f, cross["accel_hz"])),
        **{f"fused by a {lag:g} s fixed lag": mode_lags(model, lagged_ratio(lag, dt, profile))
           for lag in args.lags},
    }  # fmt: skip
    cutoff = model.chain_args[3]
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
        rows = bounds(flights[("nominal", seed, 0)], flights[("nominal", seed, args.window)],
                      flights[("actuation_only", seed, 0)], lags)  # fmt: skip
        for label, (ratio, nees) in rows.items():
            cells = " / ".join(f"{x:.2f}" for x in ratio)
            within = "yes" if ratio.max() <= 1.3 else "no"
            check = "-" if nees is None else f"{nees:.1f}"
            print(f"| {seed} | {label} | {cells} | {within} | {check} |")
    print("(GLS NEES: generalised least squares on the nominal data under the row's model, ~10 "
          "for a model true to the data; one draw per seed)")  # fmt: skip


if __name__ == "__main__":
    main()
