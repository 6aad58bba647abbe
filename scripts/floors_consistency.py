"""What sets the NEES of a flight with the floors alone: the floors' weight or the random walk?

The floors (``estimator.noise_model``: R_model = c diag(f^2, t^2), the balance's model error's
long-run variance per update, measured on the noiseless flight) are the whole measurement
covariance of a flight without sensor or actuation noise, and its NEES reads 1.4
(docs/estimation_limits.md). One hypothesis: the model error is slow (lag-1 correlation 0.98) and
the regressor oscillates, so its long-run variance over-counts it, as it would the IMU's channels.
This script tests it, and the other candidate, the parameters' random walk (``process_std_rel``):

1. The model error per update on the noiseless flight (``ideal``, 2 robots, figure8_tumble, 90 s,
   seed 0, the benchmark's cargo as in ``estimation_limits.py``): r_k = z_k - Y_k pi - b_k at the
   true parameters pi, its autocovariance C_m(L) (about the true zero, over updates L apart), its
   long-run variance (Bartlett over 32 updates, the floors' measure) and the regressor-weighted
   W_m = C_m(0) + sum_L rho(L) (C_m(L) + C_m(L)^T) (``motion.lag_weighted_covariance``), rho the
   estimator's own autocorrelation of its regressor (``RegressorAutocorrelation``); the sum ends at
   the lags the estimator tracks (``n_lags``), and the error's correlation there is printed.
2. Weighted least squares on those updates (the filter without prior and random walk), with the
   floors and with W_m as R: its realised NEES, and the NEES it expects for noise with the
   measured C_m(L) independent of the regressor, tr(F^-1 B), F = sum_k Y_k^T R_k^-1 Y_k,
   B = sum_kl Y_k^T R_k^-1 C_m(l - k) R_l^-1 Y_l (over the tracked lags, as W_m): 10 when R
   weighs the error right. This is exact for any regressor, where W_m is exact for a scalar one.
3. The filter with each source alone (``estimation_limits.py --alone``'s profiles) as it is, with
   its floors replaced by W_m (robot k's C_m(L), at the filter's running rho, every update:
   ``weigh_floors``), without the random walk (``process_std_rel=0``), and both: NEES per seed
   and robot and the mean against its 95 % band; the filter's variance with the random walk over
   that without it along each direction (the pair's generalised eigenvalues); with every source
   and with perfect sensors, robot 0's Cramer-Rao bound on the principal moments, and their
   ratio (the 1.3x target):

    .venv/bin/python scripts/floors_consistency.py --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one thread per worker

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmark_estimation as bench  # noqa: E402
import estimation_limits as limits  # noqa: E402  (registers the limits_* profiles)
import numpy as np  # noqa: E402
from scipy.linalg import eigh  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from astrocargo.estimator.motion import lag_weighted_covariance  # noqa: E402

CONTROL_HZ = 62.5
# The parameters' random walk of earlier versions (``process_std_rel``; now 0 by default).
FORMER_PROCESS_STD_REL = 1e-5
# (name, the floors replaced by W_m, the former random walk on)
FILTERS = (
    ("walk 1e-5", False, True),
    ("floors W_m", True, True),
    ("no random walk", False, False),
    ("W_m, no walk", True, False),
)
BARTLETT_LAGS = 32  # the floors' long-run variance (``NoiseModel``'s docstring)


def weigh_floors(est, model_cov: np.ndarray) -> None:
    """Replace the estimator's floors, before each update, by W_m at its regressor's running
    autocorrelation (``model_cov`` C_m (n_lags + 1, 6, 6); a diagnostic on the estimator's
    internals: ``meas_cov`` holds the floors)."""
    measure = est._measurement

    def measurement(stamp, *args):
        est.meas_cov = lag_weighted_covariance(model_cov, est.noise.autocorrelation.rho())
        return measure(stamp, *args)

    est._measurement = measurement


def _record_stamps(est) -> list[int]:
    """The stamps of the estimator's accepted updates, in its log's order."""
    stamps, box = [], {}
    measure, update = est._measurement, est.ukf.update_linear

    def measurement(stamp, *args):
        box["stamp"] = stamp
        return measure(stamp, *args)

    def update_linear(*args):
        result = update(*args)
        if result.accepted:
            stamps.append(box["stamp"])
        return result

    est._measurement, est.ukf.update_linear = measurement, update_linear
    return stamps


def fly(job) -> list[dict]:
    """One flight of (profile, seed, weighed, walk, duration, C_m per robot or None); per robot
    its NEES, recorded updates (z, Y, b, R), their update counts, the truth, the regressor's
    autocorrelation and the floors."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    noise, seed, weighed, walk, duration, model_covs = job
    # The filter's own covariance P (``encoders_over_time`` off): this study is of P's weights.
    kwargs = {
        "record": True, "process_std_rel": FORMER_PROCESS_STD_REL if walk else 0.0,
        "encoders_over_time": False,
    }  # fmt: skip
    env = astrobee_cargo_v0.parallel_env(
        n_robots=2, trajectory="figure8_tumble", noise=noise, cargo_mass_kg=bench.CARGO_MASS,
        cargo_com_m=bench.CARGO_COM, cargo_inertia=bench.CARGO_INERTIA,
        max_cycles=int(round(duration * CONTROL_HZ)), estimator_kwargs=kwargs,
    )  # fmt: skip
    obs, _ = env.reset(seed=seed)
    if weighed:
        for est, model_cov in zip(env.sim.estimators, model_covs, strict=True):
            weigh_floors(est, model_cov)
    stamps = [_record_stamps(est) for est in env.sim.estimators]
    controller = ObservationController.for_env(env)
    while env.agents:
        obs, *_ = env.step(controller.predict(obs)[0])
    rows = []
    for est, truth, st in zip(env.sim.estimators, env.sim.true_params_grasp, stamps, strict=True):
        err = est.params_mean() - truth
        rows.append({
            "nees": float(err @ np.linalg.solve(est.params_cov(), err)), "log": est.log,
            "cov": est.params_cov(),
            "counts": np.array(st) // est.update_every, "truth": truth,
            "rho": est.noise.autocorrelation.rho(), "floors": est.noise.floor_cov,
        })  # fmt: skip
    env.close()
    return rows


def model_error_autocovariance(row: dict, n_lags: int) -> np.ndarray:
    """C_m(L) (n_lags + 1, 6, 6): mean of r_k r_(k+L)^T over the recorded updates L apart, r the
    residual at the true parameters (about zero: the error's mean is error too)."""
    r = np.array([z - y @ row["truth"] - b for z, y, b, _ in row["log"]])
    counts = row["counts"]
    full = np.full((counts[-1] + 1, 6), np.nan)
    full[counts] = r
    out = np.zeros((n_lags + 1, 6, 6))
    for lag in range(n_lags + 1):
        a, b = full[: len(full) - lag], full[lag:]
        both = ~np.isnan(a[:, 0]) & ~np.isnan(b[:, 0])
        out[lag] = a[both].T @ b[both] / both.sum()
    return out


def least_squares_nees(log: list, counts: np.ndarray, truth, model_cov, cov=None):
    """Weighted least squares on ``log`` with R_k (or ``cov`` for every update): its realised
    NEES under F^-1, and its expected NEES tr(F^-1 B) for noise of autocovariance ``model_cov``
    (n_lags + 1, 6, 6), zero beyond, independent of the regressor (module docstring, item 2):
    exact, for updates at the update ``counts``."""
    y = np.array([u[1] for u in log])
    r = np.array([z - a @ truth - b for z, a, b, _ in log])
    covs = np.array([u[3] if cov is None else cov for u in log])
    g = np.linalg.solve(covs, y)  # R_k^-1 Y_k
    info = np.einsum("kji,kjl->il", y, g)
    err = np.linalg.solve(info, np.einsum("kji,kj->i", g, r))
    lag = counts[None, :] - counts[:, None]
    spread = np.zeros((10, 10))
    for step in range(model_cov.shape[0]):
        k, m = np.nonzero(lag == step)
        term = np.einsum("kai,ab,kbj->ij", g[k], model_cov[step], g[m])
        spread += term if step == 0 else term + term.T
    return float(err @ info @ err), float(np.trace(np.linalg.solve(info, spread)))


def bound_ratio(nominal: dict, perfect: dict) -> np.ndarray:
    """Robot 0's Cramer-Rao bound on the principal moments, nominal over perfect sensors."""
    from astrocargo.estimator.baselines import Recording, crlb

    bounds = [crlb(Recording.from_log(r["log"]), r["truth"]) for r in (nominal, perfect)]
    return bounds[0]["std_principal"] / bounds[1]["std_principal"]  # the same truth


def print_model_error(rows: list[dict], tail_lags: list[int]) -> list[np.ndarray]:
    """Item 1 and 2 of the module docstring for the noiseless flight, the expected NEES also with
    C_m(L) summed out to each of ``tail_lags`` (the error's correlation beyond the tracked lags,
    which W_m cannot weigh: rho is not known there); returns C_m per robot."""
    covs = []
    print("noiseless flight (ideal, seed 0): the model error per update, robot by robot")
    for k, row in enumerate(rows):
        n_lags = row["rho"].size - 1
        c_all = model_error_autocovariance(row, max(n_lags, BARTLETT_LAGS, *tail_lags))
        c_m = c_all[: n_lags + 1]
        covs.append(c_m)
        var = np.diag(c_m[0])
        corr = {lag: np.diag(c_m[lag]) / var for lag in (1, 5, 10, 20, n_lags)}
        taper = 1 - np.arange(1, BARTLETT_LAGS + 1) / (BARTLETT_LAGS + 1)
        tail = c_all[1 : BARTLETT_LAGS + 1] + c_all[1 : BARTLETT_LAGS + 1].transpose(0, 2, 1)
        long_run = c_m[0] + np.einsum("l,lab->ab", taper, tail)
        weighted = lag_weighted_covariance(c_m, row["rho"])
        rms = np.array2string(np.sqrt(var), precision=2)
        print(f"robot {k}: rms per update (N x3, N m x3) {rms}")
        for lag, c in corr.items():
            print(f"  correlation at lag {lag}: {np.array2string(c, precision=2)}")
        print(f"  regressor's rho at lags 1, 10, 20, 40, {n_lags}: "
              f"{np.array2string(row['rho'][[1, 10, 20, 40, n_lags]], precision=2)}")  # fmt: skip
        for name, cov in (("long-run (Bartlett 32)", long_run), ("W_m", weighted)):
            ratio = np.diag(cov) / np.diag(row["floors"])
            print(f"  {name} / floors: {np.array2string(ratio, precision=2)}")
        for name, cov in (("floors", None), ("W_m", weighted)):
            real, expected = least_squares_nees(row["log"], row["counts"], row["truth"], c_m, cov)
            longer = [
                least_squares_nees(row["log"], row["counts"], row["truth"], c_all[: n + 1], cov)[1]
                for n in tail_lags
            ]
            tails = ", ".join(f"{x:.1f} to {n}" for x, n in zip(longer, tail_lags, strict=True))
            print(f"  least squares with R = {name}: NEES {real:.1f}, expected {expected:.1f} "
                  f"(C_m summed to lag {n_lags}; {tails})")  # fmt: skip
    return covs


def print_filters(jobs: list, results: list, seeds: list[int]) -> None:
    """Item 3: NEES per source and filter, and the bound's ratio."""
    n = len(seeds)
    low, high = (chi2.ppf(p, 10 * n) / n for p in (0.025, 0.975))
    print(f"\nNEES per source alone, seeds {seeds} (robots); 95 % band of the mean "
          f"[{low:.1f}, {high:.1f}]")  # fmt: skip
    print("| noise | filter | NEES per seed (robots) | mean | in band |")
    print("|---|---|---|---|---|")
    by_key = {(j[0], j[1], j[2], j[3]): rows for j, rows in zip(jobs, results, strict=True)}
    spread = {}
    for name, label, _ in limits.ALONE:
        for filt, weighed, walk in FILTERS:
            per_seed = [[r["nees"] for r in by_key[(f"limits_{name}", s, weighed, walk)]]
                        for s in seeds]  # fmt: skip
            mean = float(np.mean(per_seed))
            cells = "; ".join(" / ".join(f"{x:.1f}" for x in seed) for seed in per_seed)
            inside = "yes" if low <= mean <= high else "no"
            print(f"| {label} | {filt} | {cells} | {mean:.1f} | {inside} |")
        walk = [by_key[(f"limits_{name}", s, False, True)] for s in seeds]
        still = [by_key[(f"limits_{name}", s, False, False)] for s in seeds]
        pairs = [pair for w, n in zip(walk, still, strict=True) for pair in zip(w, n, strict=True)]
        ratio = [eigh(a["cov"], b["cov"], eigvals_only=True) for a, b in pairs]
        spread[label] = (np.min(ratio), np.median(ratio), np.max(ratio))
    print(
        "\nthe random walk's share: the filter's variance with it over without it along each "
        "direction (generalised eigenvalues; min, median, max over seeds and robots)"
    )
    for label, (low_r, mid_r, high_r) in spread.items():
        print(f"{label}: {low_r:.2f}, {mid_r:.2f}, {high_r:.2f}")
    print("\nrobot 0's bound, nominal / perfect sensors (I1 / I2 / I3)")
    for filt, weighed, walk in FILTERS:
        ratios = [
            bound_ratio(by_key[("limits_nominal", s, weighed, walk)][0],
                        by_key[("limits_actuation_only", s, weighed, walk)][0])
            for s in seeds
        ]  # fmt: skip
        cells = "; ".join(" / ".join(f"{x:.2f}" for x in r) for r in ratios)
        print(f"{filt}: {cells} (seeds {seeds})")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="env seeds")
    parser.add_argument("--duration", type=float, default=90.0, help="seconds per flight")
    parser.add_argument("--workers", type=int, default=2, help="processes")
    parser.add_argument(
        "--tail-lags", type=int, nargs="*", default=[120, 200, 300],
        help="the expected NEES also with the error's autocovariance summed to these lags",
    )  # fmt: skip
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    noiseless = fly(("ideal", 0, False, True, args.duration, None))
    model_covs = print_model_error(noiseless, args.tail_lags)
    jobs = [
        (f"limits_{name}", seed, weighed, walk, args.duration, model_covs)
        for name, _, _ in limits.ALONE for _, weighed, walk in FILTERS for seed in args.seeds
    ]  # fmt: skip
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(fly, jobs))
    print_filters(jobs, results, args.seeds)


if __name__ == "__main__":
    main()
