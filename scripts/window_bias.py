"""Why the over-time window leaves the NEES band: the IMU's and encoders' errors in variables.

Flies the limits' scenario (2 robots, `figure8_tumble`, 90 s) with the accelerometer alone at
``--scales`` times its `nominal` noise (``--gyro``: the gyro instead; ``--encoders S``: with the
encoders' noise at S times `nominal` too),
with the estimators' ``over_time_window`` 0 and ``--window``, and prints per robot the signed
mass error against the filter's own mass std, the first moment's z error, the NEES, and two
statistics of the recorded updates at the true parameters pi: nu_k = z_k - Y_k pi - b_k whitened
by its R_k (per update, the conditioned z', Y', b', R' with a window), its mean square per
dimension (1 for a consistent R) and its lag-1 correlation over updates (0 for white).

    .venv/bin/python scripts/window_bias.py --seeds 0 1 2
    .venv/bin/python scripts/window_bias.py --seeds 0 1 2 --encoders 1
    .venv/bin/python scripts/window_bias.py --seeds 0 --scales 1 --encoders 0.5 1 2
    .venv/bin/python scripts/window_bias.py --seeds 0 --scales 1 4 16 --gyro

An unbiased error grows as the noise's std, as does the filter's std; a bias from errors in
variables (the regressor's noise times the balance's own) grows as its square. The mass error's
ratio to its std staying put over the scales says noise; growing with them, bias.
"""

from __future__ import annotations

import argparse
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one thread per worker

import numpy as np  # noqa: E402

from astrocargo.envs import sensors  # noqa: E402

NOMINAL = sensors.NOISE_PROFILES["nominal"]
_SILENT = replace(
    NOMINAL, accel_std=0.0, gyro_std=0.0, position_std_m=0.0, attitude_std_rad=0.0,
    encoder_std_rad=0.0, force_std_n=0.0, force_rel=0.0, torque_std_nm=0.0, torque_rel=0.0,
)  # fmt: skip
CONTROL_HZ = 62.5


def _profile(scale: float, encoders: float, gyro: bool) -> str:
    """Register (in this process and the workers it forks) the accelerometer (or the gyro) at
    ``scale`` times `nominal`, the encoders at ``encoders`` times."""
    name = f"window_bias_{'g' if gyro else 'a'}{scale:g}_e{encoders:g}"
    sensors.NOISE_PROFILES[name] = replace(
        _SILENT,
        accel_std=0.0 if gyro else scale * NOMINAL.accel_std,
        gyro_std=scale * NOMINAL.gyro_std if gyro else 0.0,
        encoder_std_rad=encoders * NOMINAL.encoder_std_rad,
    )
    return name


def innovation_stats(log: list, pi: np.ndarray) -> tuple[float, float]:
    """Mean square per dimension and lag-1 correlation over updates of the recorded updates'
    whitened residual at ``pi``: w_k = L_k^-1 (z_k - Y_k pi - b_k), L_k L_k^T = R_k."""
    w = np.array([np.linalg.solve(np.linalg.cholesky(r), z - y @ pi - b) for z, y, b, r in log])
    square = float(np.mean(w**2))
    return square, float(np.mean(np.sum(w[:-1] * w[1:], axis=1)) / 6 / square)


def fly(job: tuple[str, int, int, float]) -> list[dict]:
    """One flight; per robot its mass error and std, z first-moment error, NEES, residual."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    noise, seed, window, duration = job
    env = astrobee_cargo_v0.parallel_env(
        n_robots=2, trajectory="figure8_tumble", noise=noise,
        max_cycles=int(round(duration * CONTROL_HZ)),
        estimator_kwargs={"record": True, "over_time_window": window},
    )  # fmt: skip
    obs, _ = env.reset(seed=seed)
    controller = ObservationController.for_env(env)
    while env.agents:
        obs, *_ = env.step(controller.predict(obs)[0])
    rows = []
    for est, truth in zip(env.sim.estimators, env.sim.true_params_grasp, strict=True):
        err, cov = est.params_mean() - truth, est.params_cov()
        rows.append({
            "mass_err": err[0], "mass_std": np.sqrt(cov[0, 0]), "hz_err": err[3],
            "nees": float(err @ np.linalg.solve(cov, err)),
            "innovation": innovation_stats(est.log, truth),
        })  # fmt: skip
    env.close()
    return rows


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="env seeds")
    parser.add_argument(
        "--scales", type=float, nargs="+", default=[0.5, 1.0, 2.0],
        help="the accelerometer's (or gyro's) noise, multiples of nominal",
    )  # fmt: skip
    parser.add_argument("--window", type=int, default=24, help="the window flown beside 0")
    parser.add_argument(
        "--encoders", type=float, nargs="+", default=[0.0],
        help="the encoders' noise too, at these multiples of nominal (0: off)",
    )  # fmt: skip
    parser.add_argument("--gyro", action="store_true", help="scale the gyro, not the accelerometer")
    parser.add_argument("--duration", type=float, default=90.0, help="seconds per flight")
    parser.add_argument("--workers", type=int, default=2, help="processes")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    jobs = [
        (_profile(scale, enc, args.gyro), seed, window, args.duration)
        for enc in args.encoders for scale in args.scales for window in (0, args.window)
        for seed in args.seeds
    ]  # fmt: skip
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(fly, jobs))
    source = "gyro" if args.gyro else "accel"
    print(f"2 robots, figure8_tumble, {args.duration:g} s; noise x nominal; per robot (0 / 1)")
    print(
        f"| {source} x | encoders x | window | seed | mass error (g) | mass std (g) | error / std "
        "| h_z error (g m) | NEES | nu mean square | nu lag-1 corr |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (noise, seed, window, _), rows in zip(jobs, results, strict=True):
        profile = sensors.NOISE_PROFILES[noise]
        if args.gyro:
            scale = profile.gyro_std / NOMINAL.gyro_std
        else:
            scale = profile.accel_std / NOMINAL.accel_std
        enc = profile.encoder_std_rad / NOMINAL.encoder_std_rad

        def cells(fmt, key, rows=rows):
            return " / ".join(fmt.format(key(r)) for r in rows)

        print(
            f"| {scale:g} | {enc:g} | {window} | {seed} "
            f"| {cells('{:+.1f}', lambda r: 1e3 * r['mass_err'])} "
            f"| {cells('{:.1f}', lambda r: 1e3 * r['mass_std'])} "
            f"| {cells('{:+.1f}', lambda r: r['mass_err'] / r['mass_std'])} "
            f"| {cells('{:+.1f}', lambda r: 1e3 * r['hz_err'])} "
            f"| {cells('{:.1f}', lambda r: r['nees'])} "
            f"| {cells('{:.2f}', lambda r: r['innovation'][0])} "
            f"| {cells('{:+.2f}', lambda r: r['innovation'][1])} |"
        )


if __name__ == "__main__":
    main()
