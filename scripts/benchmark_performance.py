"""Performance benchmarks of astrocargo, one section per component.

Sections:
- estimator: one predict + update of `InertialParamUKF` against filterpy's stock
  `UnscentedKalmanFilter` given the very same per-point measurement function, on a seeded
  sequence of cargo-inertia measurements (n = 10 states, m = 6 wrench components).
- env: one `env.step` (N = 1, 2, 4, 8 robots; estimators on and off) against bare MuJoCo
  `mj_step(nstep=frame_skip)` of the same model from the same state; real-time factor = control
  period / mean step time; step_over_physics = mean step / mean physics step (estimators on, and
  off as step_over_physics_no_estimator; the same of medians as ..._median, robust to other jobs
  on a shared machine); the same ratios of this thread's CPU time (`time.thread_time_ns` read
  around the same calls, outside the wall-clock reads: time the thread spends descheduled while
  other processes run does not count) as step_over_physics_cpu and
  step_over_physics_no_estimator_cpu (means) and ..._cpu_median (a thread-time read is a
  system call, part of whose cost lands inside each interval, step and physics alike: it pulls
  the CPU ratios slightly towards 1); reset_ms = mean `env.reset()` time (reset_median_ms:
  median).
- controller: `ObservationController.predict` beside the `env.step` it drives, in one loop
  (2 and 3 robots); predict_over_step = mean predict / mean step.
- sb3_loop: environment steps per second per copy through the SB3 adapter of envs/wrappers.py
  (`SharedPolicyVecEnv`, set up as scripts/train.py does on its task figure8_10s, one copy): a
  plain loop of PPO's `predict` and `VecEnv.step`, and the same loop with zero actions (the
  adapter and env alone); per second of wall time and per second of the process's CPU time
  (steps_per_cpu_s, adapter_steps_per_cpu_s: time lost to other jobs left out).
- training: environment steps per second inside SB3's loop (PPO rollouts and updates, set up
  as scripts/train.py does) for 1 and 2 environment copies (2 copies: in-process, and one
  subprocess per copy as subprocess_steps_per_s).
- numba: wall time of a fresh process that imports the package, builds a 2-robot env, resets it
  and steps it once, twice with the same empty NUMBA_CACHE_DIR: the first run compiles every
  kernel and writes the cache, the second loads it (first_s, cached_s, compile_s = difference).

Every section uses the public API only (`astrobee_cargo_v0.parallel_env`, `env.sim`'s model,
data and control period, `ObservationController.for_env`, scripts/train.py's set-up).

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


ENV_RESETS = 5  # timed resets per robot count (after one untimed)


def _make_env(n_robots: int, estimators: bool = True, **kwargs):
    """``astrobee_cargo_v0.parallel_env`` with nominal noise."""
    from astrocargo.envs import astrobee_cargo_v0

    return astrobee_cargo_v0.parallel_env(
        n_robots=n_robots, noise="nominal", estimators=estimators, **kwargs
    )


def _env_step_times_ns(n_robots: int, estimators: bool) -> tuple[np.ndarray, np.ndarray, object]:
    """Wall and thread CPU time of each of ENV_STEPS env steps (after ENV_WARMUP_STEPS), ns,
    and the env."""
    env = _make_env(
        n_robots,
        estimators=estimators,
        observe_estimates=estimators,
        max_cycles=10 * (ENV_WARMUP_STEPS + ENV_STEPS),
    )
    rng = np.random.default_rng(SEED)
    # Smooth, small actions (no wall contact within the run): thrust and arm both move.
    freq = rng.uniform(0.05, 0.3, (n_robots, 8))
    phase = rng.uniform(0.0, 2 * np.pi, (n_robots, 8))
    env.reset(seed=SEED)
    times, cpu_times = [], []
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(ENV_WARMUP_STEPS + ENV_STEPS):
            a = 0.2 * np.sin(2 * np.pi * freq * k * env.sim.dt_s + phase)
            actions = dict(zip(env.possible_agents, a, strict=True))
            c0 = time.thread_time_ns()
            t0 = time.perf_counter_ns()
            env.step(actions)
            t1 = time.perf_counter_ns()
            c1 = time.thread_time_ns()
            if k >= ENV_WARMUP_STEPS:
                times.append(t1 - t0)
                cpu_times.append(c1 - c0)
            if not env.agents:
                raise RuntimeError(f"benchmark episode ended early at step {k}")
    finally:
        if gc_was_enabled:
            gc.enable()
    return np.array(times), np.array(cpu_times), env


def _frame_skip(sim) -> int:
    """Physics steps per control step: ``sim.frame_skip``, else the control period over MuJoCo's
    time step."""
    frame_skip = getattr(sim, "frame_skip", None)
    return int(frame_skip) if frame_skip else max(1, round(sim.dt_s / sim.model.opt.timestep))


def _physics_step_times_ns(env) -> tuple[np.ndarray, np.ndarray]:
    """Wall and thread CPU time (ns) of bare mj_step(nstep=frame_skip) of the env's own model
    from its current state."""
    import mujoco

    model, data = env.sim.model, env.sim.data
    nstep = _frame_skip(env.sim)
    times, cpu_times = [], []
    for k in range(ENV_WARMUP_STEPS + ENV_STEPS):
        c0 = time.thread_time_ns()
        t0 = time.perf_counter_ns()
        mujoco.mj_step(model, data, nstep=nstep)
        t1 = time.perf_counter_ns()
        c1 = time.thread_time_ns()
        if k >= ENV_WARMUP_STEPS:
            times.append(t1 - t0)
            cpu_times.append(c1 - c0)
    return np.array(times), np.array(cpu_times)


def _reset_times_ms(n_robots: int) -> np.ndarray:
    """Wall time of ENV_RESETS ``env.reset`` calls (new seeds, after one untimed reset), ms."""
    env = _make_env(n_robots)
    env.reset(seed=SEED)
    times = []
    for k in range(ENV_RESETS):
        t0 = time.perf_counter_ns()
        env.reset(seed=SEED + 1 + k)
        times.append((time.perf_counter_ns() - t0) / 1e6)
    env.close()
    return np.array(times)


def bench_env() -> dict[str, dict[str, float]]:
    """Microseconds per env step (median and mean), real-time factors, the step's cost over
    MuJoCo's physics alone and the time of a reset, per robot count."""
    results: dict[str, dict[str, float]] = {}
    print(
        f"env: {ENV_STEPS} steps after {ENV_WARMUP_STEPS} warm-up steps, nominal noise, seed "
        f"{SEED}, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}; rtf = control "
        f"period / mean step time; /phys = mean step / mean mj_step; cpu /phys: the same of "
        f"thread CPU time; reset: mean of "
        f"{ENV_RESETS}"
    )
    print(
        f"  {'N':>2} {'step us':>9} {'mean us':>9} {'rtf':>7} {'no-est us':>10} {'mean us':>9} "
        f"{'rtf':>7} {'mj_step us':>11} {'rtf':>8} {'/phys':>6} {'no-est/phys':>12} "
        f"{'median /phys':>13} {'cpu /phys':>12} "
        f"{'reset ms':>9}"
    )
    for n in ENV_ROBOTS:
        on, on_cpu, env = _env_step_times_ns(n, estimators=True)
        off, off_cpu, _ = _env_step_times_ns(n, estimators=False)
        physics, physics_cpu = _physics_step_times_ns(env)
        resets = _reset_times_ms(n)
        dt_us = env.sim.dt_s * 1e6
        physics_mean_us = float(np.mean(physics)) / 1e3
        row = {
            "step_us": float(np.median(on)) / 1e3,
            "step_mean_us": float(np.mean(on)) / 1e3,
            "rtf": dt_us / (float(np.mean(on)) / 1e3),
            "step_no_estimator_us": float(np.median(off)) / 1e3,
            "step_no_estimator_mean_us": float(np.mean(off)) / 1e3,
            "rtf_no_estimator": dt_us / (float(np.mean(off)) / 1e3),
            "physics_only_us": float(np.median(physics)) / 1e3,
            "physics_only_mean_us": physics_mean_us,
            "rtf_physics_only": dt_us / physics_mean_us,
            "step_over_physics": float(np.mean(on)) / 1e3 / physics_mean_us,
            "step_over_physics_no_estimator": float(np.mean(off)) / 1e3 / physics_mean_us,
            # Medians over medians: the same ratios, robust to other jobs on a shared machine.
            "step_over_physics_median": float(np.median(on) / np.median(physics)),
            "step_over_physics_no_estimator_median": float(np.median(off) / np.median(physics)),
            # This thread's CPU time: time descheduled while other processes run is left out.
            "step_over_physics_cpu": float(np.mean(on_cpu) / np.mean(physics_cpu)),
            "step_over_physics_no_estimator_cpu": float(np.mean(off_cpu) / np.mean(physics_cpu)),
            "step_over_physics_cpu_median": float(np.median(on_cpu) / np.median(physics_cpu)),
            "step_over_physics_no_estimator_cpu_median": float(
                np.median(off_cpu) / np.median(physics_cpu)
            ),
            "reset_ms": float(np.mean(resets)),
            "reset_median_ms": float(np.median(resets)),
        }
        results[str(n)] = row
        print(
            f"  {n:>2} {row['step_us']:9.0f} {row['step_mean_us']:9.0f} {row['rtf']:7.1f} "
            f"{row['step_no_estimator_us']:10.0f} {row['step_no_estimator_mean_us']:9.0f} "
            f"{row['rtf_no_estimator']:7.1f} {row['physics_only_us']:11.1f} "
            f"{row['rtf_physics_only']:8.0f} {row['step_over_physics']:6.1f} "
            f"{row['step_over_physics_no_estimator']:12.1f} "
            f"{row['step_over_physics_median']:6.1f} / "
            f"{row['step_over_physics_no_estimator_median']:4.1f} "
            f"{row['step_over_physics_cpu']:6.2f} / "
            f"{row['step_over_physics_no_estimator_cpu']:4.2f} "
            f"{row['reset_ms']:9.1f}"
        )
    return results


CONTROLLER_ROBOTS = (2, 3)


def bench_controller() -> dict[str, dict[str, float]]:
    """The scripted controller's ``predict`` beside the ``env.step`` it drives, in one loop, per
    robot count: microseconds (mean) and their ratio."""
    from astrocargo.agents.controllers import ObservationController

    results: dict[str, dict[str, float]] = {}
    print(
        f"controller: ObservationController.predict (cargo model 'estimate') and env.step in one "
        f"loop, figure8_tumble, {ENV_STEPS} steps after {ENV_WARMUP_STEPS} warm-up, seed {SEED}"
    )
    print(f"  {'N':>2} {'predict us':>11} {'step us':>9} {'predict/step':>13}")
    for n in CONTROLLER_ROBOTS:
        env = _make_env(
            n, trajectory="figure8_tumble", max_cycles=10 * (ENV_WARMUP_STEPS + ENV_STEPS)
        )
        obs, _ = env.reset(seed=SEED)
        controller = ObservationController.for_env(env, "estimate")
        predict_ns, step_ns = [], []
        gc_was_enabled = gc.isenabled()
        gc.disable()
        try:
            for k in range(ENV_WARMUP_STEPS + ENV_STEPS):
                t0 = time.perf_counter_ns()
                actions, _ = controller.predict(obs)
                t1 = time.perf_counter_ns()
                obs, *_ = env.step(actions)
                t2 = time.perf_counter_ns()
                if k >= ENV_WARMUP_STEPS:
                    predict_ns.append(t1 - t0)
                    step_ns.append(t2 - t1)
                if not env.agents:
                    raise RuntimeError(f"benchmark episode ended early at step {k}")
        finally:
            if gc_was_enabled:
                gc.enable()
        env.close()
        row = {
            "predict_us": float(np.mean(predict_ns)) / 1e3,
            "step_us": float(np.mean(step_ns)) / 1e3,
        }
        row["predict_over_step"] = row["predict_us"] / row["step_us"]
        results[str(n)] = row
        print(
            f"  {n:>2} {row['predict_us']:11.0f} {row['step_us']:9.0f} "
            f"{row['predict_over_step']:13.2f}"
        )
    return results


SB3_LOOP_WARMUP_STEPS = 200
SB3_LOOP_STEPS = 2000


# The SB3 sections time train.py's first task (figure8_10s: the env itself at 12.5 Hz, one env step
# per decision), the one their earlier figures were measured on; the default task ("cargo") runs
# the env at 62.5 Hz and repeats each decision for 5 env steps.
BENCH_TASK = "figure8_10s"


def bench_sb3_loop() -> dict[str, float]:
    """Environment steps per second per copy through the SB3 adapter, one copy set up as
    scripts/train.py does: PPO's predict + VecEnv.step, and zero actions + VecEnv.step."""
    train = _load_train_script()
    args = train.build_parser().parse_args(
        ["--copies", "1", "--no-progress-bar", "--seed", str(SEED), "--task", BENCH_TASK]
    )
    model, _ = train.build_model(args, SEED)
    venv = model.get_env()
    zeros = np.zeros((venv.num_envs, *venv.action_space.shape), dtype=venv.action_space.dtype)

    def loop(act) -> tuple[float, float]:
        """Steps per second of wall time and of the process's CPU time."""
        obs = venv.reset()
        for _ in range(SB3_LOOP_WARMUP_STEPS):
            obs, *_ = venv.step(act(obs))
        start, cpu_start = time.perf_counter(), time.process_time()
        for _ in range(SB3_LOOP_STEPS):
            obs, *_ = venv.step(act(obs))
        cpu = time.process_time() - cpu_start
        return SB3_LOOP_STEPS / (time.perf_counter() - start), SB3_LOOP_STEPS / cpu

    policy, policy_cpu = loop(lambda obs: model.predict(obs, deterministic=False)[0])
    adapter, adapter_cpu = loop(lambda obs: zeros)
    venv.close()
    print(
        f"sb3_loop: one copy of scripts/train.py's set-up ({args.robots} robots, "
        f"{'with' if args.estimates else 'without'} estimates, VecNormalize, task {BENCH_TASK}), "
        f"{SB3_LOOP_STEPS} steps after {SB3_LOOP_WARMUP_STEPS}; env steps/s per copy, of wall "
        f"time and of the process's CPU time (robust to other jobs on a shared machine)"
    )
    print(f"  {'':20} {'wall':>9} {'cpu':>9}")
    print(f"  PPO predict + step   {policy:9.0f} {policy_cpu:9.0f}")
    print(f"  zero actions + step  {adapter:9.0f} {adapter_cpu:9.0f}")
    return {
        "steps_per_s": policy,
        "adapter_steps_per_s": adapter,
        "steps_per_cpu_s": policy_cpu,
        "adapter_steps_per_cpu_s": adapter_cpu,
        "robots": args.robots,
    }


NUMBA_PROBE = """
import time
start = time.perf_counter()
import numpy as np
from astrocargo.envs import astrobee_cargo_v0
env = astrobee_cargo_v0.parallel_env(n_robots=2, noise="nominal")
env.reset(seed=0)
env.step({a: np.zeros(env.action_space(a).shape) for a in env.agents})
print(time.perf_counter() - start)
"""


def bench_numba() -> dict[str, float]:
    """Seconds for a fresh process to import the package, build, reset and step a 2-robot env:
    first with an empty numba cache (every @njit(cache=True) kernel compiles and is written to
    it), then again with that cache."""
    import subprocess
    import tempfile

    def probe(cache_dir: str) -> float:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
        out = subprocess.run(
            [sys.executable, "-c", NUMBA_PROBE],
            env=env,
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        )
        return float(out.stdout.strip().splitlines()[-1])

    with tempfile.TemporaryDirectory(prefix="numba_cache_") as cache_dir:
        first = probe(cache_dir)
        cached = probe(cache_dir)
        n_files = sum(len(files) for _, _, files in os.walk(cache_dir))
    print(
        f"numba: fresh process importing astrocargo, building, resetting and stepping a 2-robot "
        f"env; NUMBA_CACHE_DIR a new empty folder ({n_files} cache files written)"
    )
    print(f"  first run (compiles)  {first:7.2f} s")
    print(f"  second run (cached)   {cached:7.2f} s")
    print(f"  compile time          {first - cached:7.2f} s")
    return {
        "first_s": first,
        "cached_s": cached,
        "compile_s": first - cached,
        "cache_files": n_files,
    }


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
        f"task {BENCH_TASK}), {TRAIN_ROLLOUTS} rollouts timed after "
        f"{TRAIN_WARMUP_ROLLOUTS} warm-up, "
        f"seed {SEED}; an environment step is one control step of one copy (2 samples)"
    )
    print(f"  {'copies':>6} {'env steps/s':>12} {'samples/s':>10} {'rollout':>9} {'where':>11}")
    for copies in TRAIN_COPIES:
        for subprocess in (False, True) if copies > 1 else (False,):
            argv = ["--copies", str(copies), "--no-progress-bar", "--seed", str(SEED)]
            argv += ["--task", BENCH_TASK]
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
    "controller": bench_controller,
    "sb3_loop": bench_sb3_loop,
    "training": bench_training,
    "numba": bench_numba,
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
