"""Performance benchmarks of astrocargo, one section per component.

Sections:
- estimator: one predict + update of `InertialParamUKF` against filterpy's stock
  `UnscentedKalmanFilter` given the very same per-point measurement function, on a seeded
  sequence of cargo-inertia measurements (n = 10 states, m = 6 wrench components).
- env: one `AstrobeeCargoEnv.step` (N = 1, 2, 4 robots; estimators on and off) against bare
  MuJoCo `mj_step(nstep=frame_skip)` of the same model; real-time factor = control period / mean
  step time.
- training: environment steps per second inside SB3's loop (PPO rollouts and updates, set up
  as scripts/train.py does) for 1 and 2 environment copies (2 copies: in-process, and one
  subprocess per copy as subprocess_steps_per_s).

Usage:
    .venv/bin/python scripts/benchmark_performance.py [--only SECTION] [--json FILE]

With --json the figures are merged into FILE under the section's key (other keys are kept).

OpenBLAS is limited to one thread (unless OPENBLAS_NUM_THREADS is already set): on matrices of
size 10 its threads only add hand-offs, and on a shared 2-core machine they made the estimator's
timings swing by 3x from run to run. The stock filter runs under the same setting.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads OpenBLAS

import argparse  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py
from cli import Formatter, json_object_file  # noqa: E402

SEED = 20240601


class NotImplementedSection(Exception):
    """Raised by a section that has not been written yet."""


# --------------------------------------------------------------------------- estimator

# Estimator problem: a 4 kg box cargo held off-centre, Astrobee-scale motion, nominal wrench noise.
CARGO_MASS_KG = 4.0
CARGO_COM_M = np.array([0.03, -0.02, 0.18])
CARGO_INERTIA_COM_KGM2 = np.diag([0.030, 0.045, 0.050])
PRIOR_MASS_KG = 3.0
PRIOR_COM_M = np.array([0.0, 0.0, 0.15])
PRIOR_INERTIA_COM_KGM2 = np.diag([0.04, 0.04, 0.04])
ACC_STD_MPS2 = 0.0175
W_STD_RADPS = 0.1
WD_STD_RADPS2 = 0.05
FORCE_NOISE_STD_N = 0.005
TORQUE_NOISE_STD_NM = 5e-4
KNOWN_WRENCH_STD = 0.05  # magnitude of b: the known sub-bodies' momentum rates, N and N m


def estimator_inputs(n_steps: int, seed: int = SEED) -> tuple[np.ndarray, list[tuple]]:
    """Seeded (z, A, b, R) sequence: z = A pi_true + b + v, A the cargo's body regressor."""
    from astrocargo.estimator.inertia import params_from_mass_com_inertia
    from astrocargo.estimator.rne import body_regressor

    rng = np.random.default_rng(seed)
    pi_true = params_from_mass_com_inertia(CARGO_MASS_KG, CARGO_COM_M, CARGO_INERTIA_COM_KGM2)
    R = np.diag([FORCE_NOISE_STD_N**2] * 3 + [TORQUE_NOISE_STD_NM**2] * 3)
    A_all = body_regressor(
        rng.normal(scale=ACC_STD_MPS2, size=(n_steps, 3)),
        rng.normal(scale=W_STD_RADPS, size=(n_steps, 3)),
        rng.normal(scale=WD_STD_RADPS2, size=(n_steps, 3)),
    )
    b_all = rng.normal(scale=KNOWN_WRENCH_STD, size=(n_steps, 6))
    noise = rng.multivariate_normal(np.zeros(6), R, size=n_steps)
    z_all = A_all @ pi_true + b_all + noise
    return pi_true, [(z_all[k], A_all[k], b_all[k], R) for k in range(n_steps)]


def bench_estimator(n_steps: int = 2000, n_warmup: int = 50) -> dict[str, float]:
    """Median microseconds per predict + update, ours and filterpy's stock UKF, interleaved."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from astrocargo.estimator.cargo_estimator import DEFAULT_PROCESS_STD_REL, prior_covariance
    from astrocargo.estimator.inertia import params_from_mass_com_inertia
    from astrocargo.estimator.ukf import InertialParamUKF

    pi_true, inputs = estimator_inputs(n_warmup + n_steps)
    prior = params_from_mass_com_inertia(PRIOR_MASS_KG, PRIOR_COM_M, PRIOR_INERTIA_COM_KGM2)
    prior_cov = prior_covariance(prior)
    process_cov = np.diag(DEFAULT_PROCESS_STD_REL**2 * np.diag(prior_cov))
    ours = InertialParamUKF(prior, prior_cov, process_cov)
    points = MerweScaledSigmaPoints(
        ours.dim_x, alpha=ours.points.alpha, beta=ours.points.beta, kappa=ours.points.kappa
    )
    stock = UnscentedKalmanFilter(
        dim_x=ours.dim_x, dim_z=ours.dim_z, dt=1.0, hx=None, fx=lambda x, dt: x, points=points
    )
    stock.x, stock.P, stock.Q = ours.x.copy(), ours.P.copy(), ours.Q.copy()

    def run_ours(z, A, b, R):
        ours.predict()
        ours.update_linear(z, A, b, R)

    def run_stock(z, A, b, R):
        # The very map update_linear uses (z = A pi + b), one sigma point at a time.
        stock.predict()
        stock.update(z, R=R, hx=lambda pi: np.dot(A, pi) + b)

    ours_ns, stock_ns = [], []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k, step_inputs in enumerate(inputs):
            # Alternate the order so that cache and frequency effects hit both alike.
            first, second = (run_ours, run_stock) if k % 2 == 0 else (run_stock, run_ours)
            t0 = time.perf_counter_ns()
            first(*step_inputs)
            t1 = time.perf_counter_ns()
            second(*step_inputs)
            t2 = time.perf_counter_ns()
            if k >= n_warmup:
                ours_t, stock_t = (t1 - t0, t2 - t1) if first is run_ours else (t2 - t1, t1 - t0)
                ours_ns.append(ours_t)
                stock_ns.append(stock_t)
    finally:
        if gc_was_enabled:
            gc.enable()

    ours_us = float(np.median(ours_ns)) / 1e3
    filterpy_us = float(np.median(stock_ns)) / 1e3
    max_state_diff = float(np.abs(ours.x - stock.x).max())
    mass_rel_error = abs(ours.params_mean()[0] - pi_true[0]) / pi_true[0]
    print(
        f"estimator: {n_steps} predict+update steps (n={ours.dim_x}, m={ours.dim_z}), "
        f"seed {SEED}, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; "
        f"{ours.n_updates} of {len(inputs)} updates accepted"
    )
    print(f"  InertialParamUKF       median {ours_us:9.1f} us")
    print(f"  filterpy stock UKF     median {filterpy_us:9.1f} us")
    print(f"  speedup                {filterpy_us / ours_us:9.1f} x")
    print(
        f"  check: max |x_ours - x_filterpy| = {max_state_diff:.1e}, "
        f"final mass error {100 * mass_rel_error:.2f} %"
    )
    return {"ours_us": ours_us, "filterpy_us": filterpy_us, "speedup": filterpy_us / ours_us}


# --------------------------------------------------------------------------- env, training


ENV_ROBOTS = (1, 2, 4, 8)
ENV_WARMUP_STEPS = 300  # past the estimators' 4 s warm-up, so UKF updates are in the timing
ENV_STEPS = 500


def _env_step_times_ns(n_robots: int, estimators: bool) -> tuple[np.ndarray, object]:
    """Wall time of each of ENV_STEPS env steps (after ENV_WARMUP_STEPS), and the env."""
    from astrocargo.envs.cargo_transport import AstrobeeCargoEnv

    env = AstrobeeCargoEnv(
        n_robots=n_robots,
        noise="nominal",
        estimators=estimators,
        observe_estimates=estimators,
        max_cycles=10 * (ENV_WARMUP_STEPS + ENV_STEPS),
    )
    rng = np.random.default_rng(SEED)
    # Smooth, small actions (no wall contact within the run): thrust and arm both move.
    freq = rng.uniform(0.05, 0.3, (n_robots, 8))
    phase = rng.uniform(0.0, 2 * np.pi, (n_robots, 8))
    env.reset(seed=SEED)
    times = []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(ENV_WARMUP_STEPS + ENV_STEPS):
            a = 0.2 * np.sin(2 * np.pi * freq * k * env.sim.dt_s + phase)
            actions = dict(zip(env.possible_agents, a, strict=True))
            t0 = time.perf_counter_ns()
            env.step(actions)
            t1 = time.perf_counter_ns()
            if k >= ENV_WARMUP_STEPS:
                times.append(t1 - t0)
            if not env.agents:
                raise RuntimeError(f"benchmark episode ended early at step {k}")
    finally:
        if gc_was_enabled:
            gc.enable()
    return np.array(times), env


def _physics_step_times_ns(env) -> np.ndarray:
    """Bare mj_step(nstep=frame_skip) of the env's own model from its current state."""
    import mujoco

    model, data = env.sim.model, env.sim.data
    times = []
    for k in range(ENV_WARMUP_STEPS + ENV_STEPS):
        t0 = time.perf_counter_ns()
        mujoco.mj_step(model, data, nstep=env.sim.frame_skip)
        t1 = time.perf_counter_ns()
        if k >= ENV_WARMUP_STEPS:
            times.append(t1 - t0)
    return np.array(times)


def bench_env() -> dict[str, dict[str, float]]:
    """Microseconds per env step (median and mean) and real-time factors, per robot count."""
    results: dict[str, dict[str, float]] = {}
    print(
        f"env: {ENV_STEPS} steps after {ENV_WARMUP_STEPS} warm-up steps, nominal noise, seed "
        f"{SEED}, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; rtf = control "
        f"period / mean step time"
    )
    print(
        f"  {'N':>2} {'step us':>9} {'mean us':>9} {'rtf':>7} {'no-est us':>10} {'mean us':>9} "
        f"{'rtf':>7} {'mj_step us':>11} {'rtf':>8}"
    )
    for n in ENV_ROBOTS:
        on, env = _env_step_times_ns(n, estimators=True)
        off, _ = _env_step_times_ns(n, estimators=False)
        physics = _physics_step_times_ns(env)
        dt_us = env.sim.dt_s * 1e6
        row = {
            "step_us": float(np.median(on)) / 1e3,
            "step_mean_us": float(np.mean(on)) / 1e3,
            "rtf": dt_us / (float(np.mean(on)) / 1e3),
            "step_no_estimator_us": float(np.median(off)) / 1e3,
            "step_no_estimator_mean_us": float(np.mean(off)) / 1e3,
            "rtf_no_estimator": dt_us / (float(np.mean(off)) / 1e3),
            "physics_only_us": float(np.median(physics)) / 1e3,
            "rtf_physics_only": dt_us / (float(np.mean(physics)) / 1e3),
        }
        results[str(n)] = row
        print(
            f"  {n:>2} {row['step_us']:9.0f} {row['step_mean_us']:9.0f} {row['rtf']:7.1f} "
            f"{row['step_no_estimator_us']:10.0f} {row['step_no_estimator_mean_us']:9.0f} "
            f"{row['rtf_no_estimator']:7.1f} {row['physics_only_us']:11.1f} "
            f"{row['rtf_physics_only']:8.0f}"
        )
    return results


TRAIN_COPIES = (1, 2)
TRAIN_WARMUP_ROLLOUTS = 1
TRAIN_ROLLOUTS = 4


def _load_train_script():
    """scripts/train.py as a module (its model set-up is what is measured)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train", Path(__file__).with_name("train.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def bench_training() -> dict[str, dict[str, float]]:
    """Environment steps per second inside SB3's PPO loop (rollouts and updates), per copies."""
    train = _load_train_script()
    results: dict[str, dict[str, float]] = {}
    print(
        f"training: PPO as scripts/train.py sets it up (2 robots, estimates observed, "
        f"LEARNING_TASK), {TRAIN_ROLLOUTS} rollouts timed after {TRAIN_WARMUP_ROLLOUTS} warm-up, "
        f"seed {SEED}; an environment step is one control step of one copy (2 samples)"
    )
    print(f"  {'copies':>6} {'env steps/s':>12} {'samples/s':>10} {'rollout':>9} {'where':>11}")
    for copies in TRAIN_COPIES:
        for subprocess in (False, True) if copies > 1 else (False,):
            argv = ["--copies", str(copies), "--no-progress-bar", "--seed", str(SEED)]
            args = train.build_parser().parse_args(argv + (["--subprocess"] if subprocess else []))
            model, _ = train.build_model(args, SEED)
            per_rollout = model.n_steps * model.get_env().num_envs
            model.learn(TRAIN_WARMUP_ROLLOUTS * per_rollout)
            start = time.perf_counter()
            model.learn(TRAIN_ROLLOUTS * per_rollout, reset_num_timesteps=False)
            wall = time.perf_counter() - start
            model.get_env().close()
            samples_per_s = TRAIN_ROLLOUTS * per_rollout / wall
            row = {
                "steps_per_s": samples_per_s / args.robots,
                "samples_per_s": samples_per_s,
                "samples_per_rollout": per_rollout,
            }
            where = "subprocess" if subprocess else "in-process"
            if subprocess:
                results[str(copies)]["subprocess_steps_per_s"] = row["steps_per_s"]
            else:
                results[str(copies)] = row
            print(
                f"  {copies:>6} {row['steps_per_s']:12.0f} {samples_per_s:10.0f} "
                f"{per_rollout:9d} {where:>11}"
            )
    return results


SECTIONS: dict[str, Callable[[], dict[str, float]]] = {
    "estimator": bench_estimator,
    "env": bench_env,
    "training": bench_training,
}


# --------------------------------------------------------------------------- CLI


def merge_json(path: Path, results: dict[str, dict[str, float]]) -> None:
    """Write results into the JSON file at path, keeping keys already there."""
    data = json.loads(path.read_text()) if path.exists() else {}
    data.update(results)
    path.write_text(json.dumps(data, indent=2) + "\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument(
        "--only", choices=sorted(SECTIONS), help="run one section (none: every section)"
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="merge results into FILE")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked before any benchmark runs: --json must be a new file or hold
    a JSON object (the results are merged into it)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.json is not None:
        json_object_file(parser, args.json, "--json")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    results: dict[str, dict[str, float]] = {}
    for name in [args.only] if args.only else list(SECTIONS):
        try:
            results[name] = SECTIONS[name]()
        except NotImplementedSection:
            print(f"{name}: benchmark not implemented yet")
            if args.only:
                return 2
    if args.json is not None and results:
        merge_json(args.json, results)
        print(f"wrote {', '.join(results)} to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
