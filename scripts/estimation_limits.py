"""What limits estimation: the Cramer-Rao bound of the same flight with one noise source at a time.

Flies one scenario (default: 2 robots, `figure8_tumble`, 90 s, seed 0, the benchmark's cargo)
under `nominal` noise and under variants of it, each with one source removed or alone, and prints
robot 0's Cramer-Rao bound (1 sigma, as `benchmark_estimation.py` computes it from the filter's
own measurements and covariance) with the UKF's errors and NEES. This is the table of
docs/estimation_limits.md:

    .venv/bin/python scripts/estimation_limits.py                       # the doc's table
    .venv/bin/python scripts/estimation_limits.py --alone --seeds 0 1 2  # NEES per source
    .venv/bin/python scripts/estimation_limits.py --trajectory excite --seeds 0 1 2

``--alone`` flies each noise source alone instead (the noise model's consistency: NEES with one
source at a time) and prints the seeds' mean NEES per source against its 95 % band; ``--pairs``
the same with two sources together. ``--over-time-window`` sets the estimators' window
(``estimator.over_time``); ``--motion-lag-s`` their fused motion's lag (``estimator.fused_motion``:
the accelerometer fused with localization, the readings fed that late; at the end of the flight
the buffered tail is fed smoothed, so that the estimate holds the whole flight, unless
``--no-flush``).
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one thread per worker

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmark_estimation as bench  # noqa: E402
import cli  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from astrocargo.envs import sensors  # noqa: E402

NOMINAL = sensors.NOISE_PROFILES["nominal"]
_NO_SENSORS = dict(
    accel_std=0.0, gyro_std=0.0, position_std_m=0.0, attitude_std_rad=0.0, encoder_std_rad=0.0
)
# Variants of `nominal`: (name, what it shows, profile).
VARIANTS = (
    ("nominal", "every source", NOMINAL),
    ("actuation_only", "perfect sensors", replace(NOMINAL, **_NO_SENSORS)),
    ("no_accelerometer", "accelerometer off", replace(NOMINAL, accel_std=0.0)),
    ("no_encoders", "encoders off", replace(NOMINAL, encoder_std_rad=0.0)),
    ("no_gyro", "gyro off", replace(NOMINAL, gyro_std=0.0)),
    (
        "no_localization",
        "localization off",
        replace(NOMINAL, position_std_m=0.0, attitude_std_rad=0.0),
    ),
    (
        "no_relative_actuation",
        "actuation's 2 % term off",
        replace(NOMINAL, force_rel=0.0, torque_rel=0.0),
    ),
    (
        "no_actuation_floor",
        "actuation's floors off",
        replace(NOMINAL, force_std_n=0.0, torque_std_nm=0.0),
    ),
)
_SILENT = replace(
    NOMINAL, **_NO_SENSORS, force_std_n=0.0, force_rel=0.0, torque_std_nm=0.0, torque_rel=0.0
)
# Each source alone: (name, label, profile).
ALONE = (
    ("accelerometer", "accelerometer alone", replace(_SILENT, accel_std=NOMINAL.accel_std)),
    ("gyro", "gyro alone", replace(_SILENT, gyro_std=NOMINAL.gyro_std)),
    ("encoders", "encoders alone", replace(_SILENT, encoder_std_rad=NOMINAL.encoder_std_rad)),
    (
        "localization",
        "localization alone",
        replace(
            _SILENT,
            position_std_m=NOMINAL.position_std_m,
            attitude_std_rad=NOMINAL.attitude_std_rad,
        ),
    ),
    ("actuation_only", "actuation alone", replace(NOMINAL, **_NO_SENSORS)),
    ("nominal", "every source", NOMINAL),
)
# Two sources together (``--pairs``): which pair moves the NEES.
PAIRS = (
    ("accel_encoders", "accelerometer and encoders",
     replace(_SILENT, accel_std=NOMINAL.accel_std, encoder_std_rad=NOMINAL.encoder_std_rad)),
    ("accel_actuation", "accelerometer and actuation",
     replace(NOMINAL, **{**_NO_SENSORS, "accel_std": NOMINAL.accel_std})),
    ("encoders_actuation", "encoders and actuation",
     replace(NOMINAL, **{**_NO_SENSORS, "encoder_std_rad": NOMINAL.encoder_std_rad})),
)  # fmt: skip
# The nominal bound's target against the perfect-sensor bound, on every principal moment.
TARGET_RATIO = 1.3
SENSOR_VARIANTS = ("no_accelerometer", "no_encoders", "no_gyro", "no_localization")
# Registered under these names in this process and in the workers it forks.
sensors.NOISE_PROFILES.update(
    {f"limits_{name}": profile for name, _, profile in VARIANTS + ALONE + PAIRS}
)


def build_parser() -> argparse.ArgumentParser:
    parser = cli.limits_parser(__doc__, 1)
    parser.add_argument("--alone", action="store_true", help="each noise source alone: NEES")
    parser.add_argument("--pairs", action="store_true", help="two sources together: NEES")
    parser.add_argument(
        "--only", nargs="+", default=None, help="fly only these variants (names as in the code)"
    )
    parser.add_argument(
        "--over-time-window", type=int, default=None,
        help="CargoEstimator's over_time_window (updates; 0 off; default: the estimator's)",
    )  # fmt: skip
    parser.add_argument(
        "--motion-lag-s", type=float, default=None,
        help="CargoEstimator's motion_lag_s (s; 0 off; default: the estimator's)",
    )  # fmt: skip
    parser.add_argument(
        "--bias-compensation", action="store_true",
        help="CargoEstimator(bias_compensation=True): the errors-in-variables bias taken out",
    )  # fmt: skip
    parser.add_argument(
        "--encoders-over-time", choices=("on", "off"), default=None,
        help="CargoEstimator's encoders_over_time: the encoders' correlation over updates in the "
        "reported covariance (default: the estimator's, on without a window)",
    )  # fmt: skip
    parser.add_argument(
        "--no-flush", action="store_true",
        help="with a lag, leave the buffered tail unfed (the estimate holds duration - lag s)",
    )  # fmt: skip
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return cli.parse_limits_args(build_parser(), argv, 1)


def _run(job: tuple[str, int, argparse.Namespace]) -> tuple[str, int, dict]:
    name, seed, args = job
    kwargs = {}
    if args.over_time_window is not None:
        kwargs["over_time_window"] = args.over_time_window
    if args.bias_compensation:
        kwargs["bias_compensation"] = True
    if args.encoders_over_time is not None:
        kwargs["encoders_over_time"] = args.encoders_over_time == "on"
    if args.motion_lag_s is not None:
        kwargs["motion_lag_s"] = args.motion_lag_s
        kwargs["localization_every"] = sensors.NOISE_PROFILES[f"limits_{name}"].localization_every
    case = bench.Case(
        name, robots=args.robots, trajectory=args.trajectory, seed=seed,
        duration=args.duration, noise=f"limits_{name}",
        extra={"estimator_kwargs": kwargs, "flush": not args.no_flush},
    )  # fmt: skip
    return name, seed, bench.run_case(case)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    variants = PAIRS if args.pairs else ALONE if args.alone else VARIANTS
    if args.only is not None:
        unknown = set(args.only) - {name for name, _, _ in variants}
        if unknown:
            raise SystemExit(f"--only: unknown variants {sorted(unknown)}")
        variants = tuple(v for v in variants if v[0] in args.only)
    jobs = [(name, seed, args) for name, _, _ in variants for seed in args.seeds]
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(_run, jobs))
    if args.alone or args.pairs:
        _print_nees(results, args, variants)
        return
    perfect = {seed: r["crlb"] for name, seed, r in results if name == "actuation_only"}
    print(
        f"{args.robots} robots, {args.trajectory}, {args.duration:g} s, seeds {args.seeds}: "
        "robot 0's Cramer-Rao bound (1 sigma) and the UKF's worst error over the robots"
    )
    print(
        "| noise | CRLB mass | CRLB CoM | CRLB principal (I1 / I2 / I3) | / perfect sensors "
        "| UKF mass | UKF CoM | UKF principal | NEES |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    labels = {name: label for name, label, _ in VARIANTS}
    for name, seed, r in results:
        c, p = r["crlb"], perfect[seed]
        pairs = zip(c["principal_rel_err"], p["principal_rel_err"], strict=True)
        ratio = " / ".join(f"{a / b:.2f}" for a, b in pairs)
        agents = list(r["agents"].values())
        worst = [max(a["principal_rel_err"][k] for a in agents) for k in range(3)]
        print(
            f"| {labels[name]} (seed {seed}) | {100 * c['mass_rel_err']:.2f} % "
            f"| {1e3 * c['com_err_m']:.2f} mm "
            f"| {' / '.join(f'{100 * x:.2f}' for x in c['principal_rel_err'])} % | {ratio} "
            f"| {100 * max(a['mass_rel_err'] for a in agents):.2f} % "
            f"| {1e3 * max(a['com_err_m'] for a in agents):.2f} mm "
            f"| {' / '.join(f'{100 * x:.1f}' for x in worst)} % "
            f"| {' / '.join(f'{nees:.1f}' for nees in (a['nees'] for a in agents))} |"
        )
    print()
    for seed in args.seeds:
        ratios = {
            name: _principal_ratio(r["crlb"], perfect[seed]) for name, s, r in results if s == seed
        }
        binding = [
            labels[n] for n, x in ratios.items() if n in SENSOR_VARIANTS and x <= TARGET_RATIO
        ]
        print(
            f"seed {seed}: nominal / perfect sensors, worst principal moment "
            f"{ratios['nominal']:.2f}"
            f" (target <= {TARGET_RATIO}); within it with one sensor removed: "
            f"{', '.join(binding) or 'none'}"
        )


def _print_nees(results: list[tuple[str, int, dict]], args: argparse.Namespace, variants) -> None:
    """Per source alone: each seed's NEES (robot by robot) and the mean over seeds and robots
    against the 95 % band of that mean (chi-square, 10 dof per robot and seed; the robots of one
    seed share the noise, so the band counts the seeds only)."""
    n = len(args.seeds)
    low, high = (chi2.ppf(p, 10 * n) / n for p in (0.025, 0.975))
    print(
        f"{args.robots} robots, {args.trajectory}, {args.duration:g} s, seeds {args.seeds}: NEES "
        f"(10 parameters) per noise source; 95 % band of the mean [{low:.1f}, "
        f"{high:.1f}]"
    )
    print("| noise | NEES per seed (robots) | mean | in band | mass, CoM, I1 / I2 / I3 (rms) |")
    print("|---|---|---|---|---|")
    for name, label, _ in variants:
        runs = [r for v, _, r in results if v == name]
        if not runs:
            continue
        per_seed = [[a["nees"] for a in r["agents"].values()] for r in runs]
        mean = float(np.mean([np.mean(x) for x in per_seed]))
        cells = "; ".join(" / ".join(f"{x:.1f}" for x in seed) for seed in per_seed)
        band = "yes" if low <= mean <= high else "no"
        print(f"| {label} | {cells} | {mean:.1f} | {band} | {_rms_errors(runs)} |")


def _rms_errors(runs: list[dict]) -> str:
    """The estimates' errors, rms over seeds and robots: mass (%), CoM (mm), principal moments
    (%)."""
    agents = [a for r in runs for a in r["agents"].values()]
    mass = 100 * np.sqrt(np.mean([a["mass_rel_err"] ** 2 for a in agents]))
    com = 1e3 * np.sqrt(np.mean([a["com_err_m"] ** 2 for a in agents]))
    principal = 100 * np.sqrt(np.mean([np.square(a["principal_rel_err"]) for a in agents], 0))
    return f"{mass:.3f} %, {com:.2f} mm, {' / '.join(f'{x:.2f}' for x in principal)} %"


def _principal_ratio(bound: dict, perfect: dict) -> float:
    """Worst ratio of two Cramer-Rao bounds over the principal moments."""
    pairs = zip(bound["principal_rel_err"], perfect["principal_rel_err"], strict=True)
    return max(a / b for a, b in pairs)


if __name__ == "__main__":
    main()
