"""Why the over-time window leaves the NEES band: the IMU's and encoders' errors in variables.

Flies the limits' scenario (2 robots, `figure8_tumble`, 90 s) with the accelerometer alone at
``--scales`` times its `nominal` noise (``--gyro``: the gyro instead; ``--encoders S``: with the
encoders' noise at S times `nominal` too), with the estimators' ``over_time_window`` 0 and
``--window``, and prints per robot the signed
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
ratio to its std staying put over the scales says noise; growing with them, bias. With a window
the last columns predict that bias from the model's own modes (``score_bias``: the expected
score of each conditioned update at the truth, through least squares on the log, over the IMU's,
the encoders' and the squared rates' modes with their covariance over time): a measured error
that matches it is that bias.
"""

from __future__ import annotations

import argparse
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one thread per worker

import numpy as np  # noqa: E402

from astrocargo.envs import sensors  # noqa: E402
from astrocargo.estimator.motion import POINT_EXTENDED  # noqa: E402
from astrocargo.estimator.over_time import IMU_MODES, conditioning_gain  # noqa: E402

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


def score_bias(coefs, d_y, balance_map, mode_lag_cov, indices, cov) -> np.ndarray:
    """E[Y'^T R'^-1 r'] (10,): the expected score of one conditioned update at the truth, for
    Y' = sum_j C_j Y_j and r' = sum_j C_j r_j over the window's updates and this one (S of them,
    C_j = ``coefs`` (S, 6, 6): -A's blocks, then I), where modes u_j (c channels, m each) move
    the regressor by sum d_Y u and the residual r = z - Y pi - b by -sum J u: ``d_y``
    (S, c, m, 6, 10), ``balance_map`` J (S, c, m, 6), Cov(u_j, u_l) = Gm(l - j) per channel
    (``mode_lag_cov`` (n_lags + 1, m, m)), ``indices`` (S,) the update counts, ``cov`` R'.
    Nonzero: errors in variables (the regressor's noise times the residual's own)."""
    n_lags = mode_lag_cov.shape[0] - 1
    lag = indices[None, :] - indices[:, None]
    gm = np.zeros((len(indices), len(indices), *mode_lag_cov.shape[1:]))
    ahead, behind = (lag >= 0) & (lag <= n_lags), (lag < 0) & (lag >= -n_lags)
    gm[ahead] = mode_lag_cov[lag[ahead]]
    gm[behind] = mode_lag_cov[-lag[behind]].transpose(0, 2, 1)
    moved_y = np.einsum("sxy,scayp->scaxp", coefs, d_y)
    moved_r = np.einsum("xy,syz,scaz->scax", np.linalg.inv(cov), coefs, balance_map)
    return -np.einsum("scaxp,stab,tcbx->p", moved_y, gm, moved_r)


def _own_modes(est, inst, msgs) -> tuple[np.ndarray, np.ndarray]:
    """This robot's modes at one update, at their per-update level: the conditioned balance map
    (N - K D) (6, n) (``NoiseModel.over_time_noise``, every own column) and d Y (n, 6, 10)."""
    noise = est.noise
    peers = [(est._relative[p].transform(), m) for p, m in zip(est.peers, msgs, strict=True)]
    own = noise.momentum_motion
    n_map, d_map, _, level = noise._team(
        own, est.ukf.params_mean(), inst.motion_jac, inst.regressor, peers
    )
    if peers:
        n_map = n_map - conditioning_gain(n_map, d_map, level, noise.mismatch_model_var) @ d_map
    scale = np.sqrt(level[: own.var.size])
    return n_map[:, : own.var.size] * scale, inst.motion_jac[1] * scale[:, None, None]


def mode_groups(noise) -> list[tuple[slice, int, int, np.ndarray]]:
    """(columns, channels, modes per channel, Gm (n_lags + 1, m, m)) of a robot's own modes:
    the IMU's (``mode_lag_cov``), the encoders' (their kernels' lag covariances in the modes of
    their per-update factor F: F^+ G(L) F^+T; white in the window's model, correlated in truth)
    and the squared rates' (white)."""
    nj, n_rate = noise._n_joints, noise._n_rate_modes
    point = noise._lag_cov[:, POINT_EXTENDED][:, :, POINT_EXTENDED]
    inverse = np.linalg.pinv(noise._point_factor)
    encoders = slice(IMU_MODES, IMU_MODES + 8 * nj)
    return [
        (slice(0, IMU_MODES), 6, 4, noise.mode_lag_cov),
        (encoders, nj, 8, inverse @ point @ inverse.T),
        (slice(encoders.stop, encoders.stop + n_rate), n_rate, 1, np.ones((1, 1, 1))),
    ]


class BiasRecorder:
    """Wraps one estimator (``over_time_window`` > 0; raw accelerometer) to keep, per used
    update, what ``score_bias`` needs (its own modes, ``_own_modes``, and the window's gain;
    estimator internals: a diagnostic), and predicts the bias of least squares on its log,
    F^-1 sum_k E[score_k], F = sum_k Y'^T R'^-1 Y', over the IMU's, the encoders' and the
    squared rates' modes (``mode_groups``)."""

    def __init__(self, est) -> None:
        self.est, self.modes, self.terms, self.used = est, {}, {}, []
        measure, noise, condition, update = (
            est._measurement, est._over_time_noise, est._window.condition, est.ukf.update_linear
        )  # fmt: skip

        def over_time_noise(inst, msgs):
            self.modes[self._stamp] = _own_modes(est, inst, msgs)
            return noise(inst, msgs)

        def conditioned(stamp, *args):
            entries = list(est._window.entries)
            out = condition(stamp, *args)
            if out[1] is not None and entries:
                s_kp = np.hstack([out[1].cross[e.stamp].T for e in entries])
                gain = np.linalg.solve(est._window._sigma, s_kp.T).T
                self.terms[stamp] = (gain, [e.stamp for e in entries])
            return out

        def measurement(stamp, *args):
            self._stamp = stamp
            return measure(stamp, *args)

        def update_linear(*args):
            result = update(*args)
            if result.accepted:
                self.used.append(self._stamp)
            return result

        est._measurement, est._over_time_noise = measurement, over_time_noise
        est._window.condition, est.ukf.update_linear = conditioned, update_linear

    def predicted_bias(self) -> np.ndarray:
        info, score = np.zeros((10, 10)), np.zeros(10)
        groups = mode_groups(self.est.noise)
        for (_, y, _, r), stamp in zip(self.est.log, self.used, strict=True):
            gain, stamps = self.terms.get(stamp, (np.zeros((6, 0)), []))
            coefs = [-gain[:, 6 * i : 6 * i + 6] for i in range(len(stamps))] + [np.eye(6)]
            stamps = [*stamps, stamp]
            balance, d_y = (np.stack(x) for x in zip(*(self.modes[s] for s in stamps), strict=True))
            indices = np.array(stamps) // self.est.update_every
            for cols, channels, m, mode_cov in groups:
                if channels:
                    shape = (len(stamps), channels, m)
                    d_yg = d_y[:, cols].reshape(*shape, 6, 10)
                    balance_g = balance[:, :, cols].transpose(0, 2, 1).reshape(*shape, 6)
                    score += score_bias(np.stack(coefs), d_yg, balance_g, mode_cov, indices, r)
            info += y.T @ np.linalg.solve(r, y)
        return np.linalg.solve(info, score)


def fly(job: tuple[str, int, int, float]) -> list[dict]:
    """One flight; per robot its mass error and std, z first-moment error, NEES, residual, and
    with a window the errors-in-variables bias predicted from its modes."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.envs import astrobee_cargo_v0

    noise, seed, window, duration = job
    env = astrobee_cargo_v0.parallel_env(
        n_robots=2, trajectory="figure8_tumble", noise=noise,
        max_cycles=int(round(duration * CONTROL_HZ)),
        # The filter's own covariance P at every window (``encoders_over_time`` off).
        estimator_kwargs={"record": True, "over_time_window": window, "encoders_over_time": False},
    )  # fmt: skip
    obs, _ = env.reset(seed=seed)
    recorders = [BiasRecorder(est) if window else None for est in env.sim.estimators]
    controller = ObservationController.for_env(env)
    while env.agents:
        obs, *_ = env.step(controller.predict(obs)[0])
    rows = []
    for est, truth, rec in zip(
        env.sim.estimators, env.sim.true_params_grasp, recorders, strict=True
    ):
        err, cov = est.params_mean() - truth, est.params_cov()
        rows.append({
            "mass_err": err[0], "mass_std": np.sqrt(cov[0, 0]), "hz_err": err[3],
            "nees": float(err @ np.linalg.solve(cov, err)),
            "innovation": innovation_stats(est.log, truth),
            "predicted": np.full(10, np.nan) if rec is None else rec.predicted_bias(),
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
        "| h_z error (g m) | NEES | nu mean square | nu lag-1 corr | predicted mass bias (g) "
        "| predicted h_z bias (g m) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
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
            f"| {cells('{:+.2f}', lambda r: r['innovation'][1])} "
            f"| {cells('{:+.1f}', lambda r: 1e3 * r['predicted'][0]) if window else '-'} "
            f"| {cells('{:+.1f}', lambda r: 1e3 * r['predicted'][3]) if window else '-'} |"
        )


if __name__ == "__main__":
    main()
