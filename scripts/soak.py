"""Soak test: one long episode with the scripted controller, checking that nothing drifts.

    .venv/bin/python scripts/soak.py --duration 3600 --robots 2

Runs ``astrobee_cargo_v0`` for ``--duration`` simulated seconds (one episode, 62.5 Hz) with the
observation-driven cooperative controller (``ObservationController``, ``--cargo-model``
"estimate": each robot uses its own live estimate; "truth": the true cargo). Every
``--check-every`` control steps it checks, for every robot's estimator, that the UKF covariance
``ukf.P`` (standard parameters) and the parameter covariance ``params_cov()`` are exactly
symmetric and positive definite (Cholesky), that the state, estimate, observations, rewards and
``state()`` are finite, and that the estimator's and the env's internal buffers (pending instants,
peer messages, own fixes, rollback snapshots, the channel's queue, the env's last messages) stay
within their bounds. Memory: the process's resident set size (RSS, /proc/self/status) at every
progress line, and the Python heap (tracemalloc) over a window of ``--trace-steps`` steps after
the warm-up and another at the end, each traced from one window earlier so that the buffers that
turn over are all traced: a leak shows as a larger live traced heap at the end of the late window
than at the end of the early one, and as RSS still rising after the warm-up.

Prints the checks, memory at start and end (and in between), the wall time and the final
estimation errors; ``--json PATH`` saves the figures. Exit status 1 if any check failed.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import resource
import sys
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see estimator/ukf.py

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py
from cli import (  # noqa: E402
    Formatter,
    nonnegative_int,
    output_file,
    positive_float,
    positive_int,
)

from astrocargo.agents.controllers import ObservationController  # noqa: E402
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs import astrobee_cargo_v0  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402

MIB = 1024.0 * 1024.0
PRINT_EVERY_S = 600.0  # one progress line per 10 simulated minutes
SYMMETRY_TOL = 0.0  # P is kept exactly symmetric by construction (estimator.ukf)
PARAMS_COV_SYMMETRY_TOL = 0.0  # params_cov() symmetrises its result
CONTROL_HZ = 62.5  # the env's default control rate
MIN_DURATION_S = 10.0  # the heap windows and at least one check need this many steps


def rss_mib() -> float:
    """Current resident set size (MiB); the peak from getrusage where /proc is missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def spd_report(matrix: np.ndarray) -> tuple[float, float, bool]:
    """(max |M - M^T|, smallest eigenvalue, Cholesky succeeded) of a square matrix."""
    asym = float(np.max(np.abs(matrix - matrix.T)))
    min_eig = float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T))[0])
    try:
        np.linalg.cholesky(matrix)
        chol = True
    except np.linalg.LinAlgError:
        chol = False
    return asym, min_eig, chol


def buffer_sizes(env) -> dict[str, int]:
    """Sizes of every per-episode container that could grow without bound."""
    sim = env.sim
    sizes = {
        "channel_queue": sum(len(v) for v in sim.channel._queue.values()),
        "channel_queue_keys": len(sim.channel._queue),
        "env_peer_msgs": sum(len(d) for d in sim.peer_msgs),
    }
    for i, est in enumerate(sim.estimators):
        sizes[f"est{i}_pending"] = len(est._pending)
        sizes[f"est{i}_peer_msgs"] = sum(len(m) for m in est._peer_msgs.values())
        sizes[f"est{i}_own_fix"] = len(est._own_fix)
        sizes[f"est{i}_snapshots"] = len(est._snapshots)
        sizes[f"est{i}_log"] = len(est.log)
    return sizes


def buffer_bounds(env) -> dict[str, int]:
    """The most each container may hold (from the settings): exceeding one is a failure."""
    sim = env.sim
    n = sim.n_robots
    latency = sim.channel.latency_steps
    bounds = {
        # A copy per receiver per message, one message per robot per update instant.
        "channel_queue": n * (n - 1) * (latency + 1),
        "channel_queue_keys": latency + 1,
        "env_peer_msgs": n * (n - 1),
    }
    for i, est in enumerate(sim.estimators):
        instants = est.history_steps // est.update_every + 2
        bounds[f"est{i}_pending"] = instants
        bounds[f"est{i}_peer_msgs"] = (n - 1) * instants
        bounds[f"est{i}_own_fix"] = instants
        bounds[f"est{i}_snapshots"] = est._snapshots.maxlen
        bounds[f"est{i}_log"] = 0 if not est.record else sys.maxsize
    return bounds


def check(env, obs, rewards) -> dict:
    """One round of checks; ``ok`` False if any failed."""
    sim = env.sim
    out: dict = {"ok": True, "estimators": []}
    finite = all(np.all(np.isfinite(o)) for o in obs.values())
    finite &= all(math.isfinite(r) for r in rewards.values())
    finite &= bool(np.all(np.isfinite(env.state())))
    for est in sim.estimators:
        p_asym, p_min, p_chol = spd_report(est.ukf.P)
        c_asym, c_min, c_chol = spd_report(est.params_cov())
        est_finite = bool(np.all(np.isfinite(est.ukf.x)) and np.all(np.isfinite(est.ukf.P)))
        est_finite &= bool(np.all(np.isfinite(est.params_mean())))
        ok = (
            est_finite
            and p_asym <= SYMMETRY_TOL
            and p_chol
            and p_min > 0
            and c_asym <= PARAMS_COV_SYMMETRY_TOL
            and c_chol
            and c_min > 0
        )
        out["estimators"].append(
            {
                "P_asym": p_asym,
                "P_min_eig": p_min,
                "P_cond": float(np.linalg.cond(est.ukf.P)),
                "params_cov_asym": c_asym,
                "params_cov_min_eig": c_min,
                "finite": est_finite,
                "ok": ok,
            }
        )
        out["ok"] &= ok
    sizes = buffer_sizes(env)
    bounds = buffer_bounds(env)
    over = {k: (v, bounds[k]) for k, v in sizes.items() if v > bounds[k]}
    out.update(finite=finite, sizes=sizes, over=over)
    out["ok"] &= finite and not over
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=Formatter
    )
    parser.add_argument("--duration", type=positive_float, default=3600.0, help="simulated seconds")
    parser.add_argument("--robots", type=int, default=2, help=f"1..{MAX_ROBOTS}")
    parser.add_argument("--cargo-model", choices=("estimate", "truth"), default="estimate")
    parser.add_argument("--noise", default="nominal", choices=sorted(NOISE_PROFILES))
    parser.add_argument("--trajectory", default="figure8_yaw", choices=Trajectory.NAMES)
    parser.add_argument("--seed", type=nonnegative_int, default=0)
    parser.add_argument(
        "--check-every", type=positive_int, default=625, help="control steps (10 s)"
    )
    parser.add_argument("--trace-steps", type=positive_int, default=5000, help="tracemalloc window")
    parser.add_argument("--json", type=Path, default=None, help="save the figures here")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked before anything runs."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
    if args.duration < MIN_DURATION_S:
        parser.error(f"--duration must be at least {MIN_DURATION_S:g} s, got {args.duration:g}")
    if round(args.duration * CONTROL_HZ) < args.check_every:
        parser.error(
            f"--duration ({args.duration:g} s) must cover at least one check "
            f"(--check-every {args.check_every} steps = {args.check_every / CONTROL_HZ:g} s)"
        )
    if args.json is not None:
        output_file(parser, args.json, "--json")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    env = astrobee_cargo_v0.parallel_env(
        n_robots=args.robots, noise=args.noise, trajectory=args.trajectory, max_cycles=10**9
    )
    n_steps = round(args.duration / env.sim.dt_s)
    trace_steps = max(1, min(args.trace_steps, n_steps // 6))
    # Heap windows: after the warm-up (the estimator's first updates, caches) and at the end;
    # tracing starts one window before each.
    windows = {
        min(n_steps // 10, 10 * trace_steps): "early",
        n_steps - 2 * trace_steps: "late",
    }
    print(
        f"soak: {args.duration:.0f} s simulated = {n_steps} steps, {args.robots} robots, "
        f"cargo_model={args.cargo_model}, noise={args.noise}, trajectory={args.trajectory}, "
        f"seed={args.seed}, checks every {args.check_every} steps"
    )
    obs, _ = env.reset(seed=args.seed)
    controller = ObservationController.for_env(env, args.cargo_model)
    gc.collect()
    memory = [{"step": 0, "sim_s": 0.0, "rss_mib": rss_mib(), "gc_objects": len(gc.get_objects())}]
    print(f"memory at start: RSS {memory[0]['rss_mib']:.1f} MiB")
    heap: dict[str, dict] = {}
    failures: list[dict] = []
    worst = {"P_min_eig": math.inf, "P_cond": 0.0, "params_cov_min_eig": math.inf}
    max_sizes: dict[str, int] = {}
    n_checks = 0
    track_max = 0.0
    reason = None
    trace: dict | None = None
    t0 = time.perf_counter()
    infos: dict = {}
    step = 0
    for step in range(1, n_steps + 1):
        if step in windows and trace is None:
            tracemalloc.start()
            trace = {"name": windows[step], "first": step + trace_steps}
        if trace is not None and step == trace["first"]:
            gc.collect()
            trace["snapshot"] = tracemalloc.take_snapshot()
            trace["traced"] = tracemalloc.get_traced_memory()[0]
        actions, _ = controller.predict(obs)
        obs, rewards, terms, truncs, infos = env.step(actions)
        track_max = max(track_max, env.sim.tracking_error()[0])
        if trace is not None and step == trace["first"] + trace_steps - 1:
            gc.collect()
            # Snapshots are traced themselves: leave tracemalloc's own allocations out.
            own = [tracemalloc.Filter(False, tracemalloc.__file__)]
            snap = tracemalloc.take_snapshot().filter_traces(own)
            traced = tracemalloc.get_traced_memory()[0]
            tracemalloc.stop()
            stats = snap.compare_to(trace["snapshot"].filter_traces(own), "lineno")
            heap[trace["name"]] = {
                "steps": trace_steps,
                "growth_bytes": int(sum(s.size_diff for s in stats)),
                "traced_start_bytes": int(trace["traced"]),
                "traced_end_bytes": int(traced),
                "top": [str(s) for s in stats[:3]],
            }
            trace = None
        if step % args.check_every == 0 or step == n_steps or not env.agents:
            result = check(env, obs, rewards)
            n_checks += 1
            for e in result["estimators"]:
                worst["P_min_eig"] = min(worst["P_min_eig"], e["P_min_eig"])
                worst["P_cond"] = max(worst["P_cond"], e["P_cond"])
                worst["params_cov_min_eig"] = min(
                    worst["params_cov_min_eig"], e["params_cov_min_eig"]
                )
            for k, v in result["sizes"].items():
                max_sizes[k] = max(max_sizes.get(k, 0), v)
            if not result["ok"]:
                failures.append({"step": step, **result})
                print(f"CHECK FAILED at step {step}: {result}", flush=True)
            sim_s = step * env.sim.dt_s
            if step % round(PRINT_EVERY_S / env.sim.dt_s) < args.check_every or step == n_steps:
                memory.append(
                    {
                        "step": step,
                        "sim_s": sim_s,
                        "rss_mib": rss_mib(),
                        "gc_objects": len(gc.get_objects()),
                    }
                )
                info = infos[env.possible_agents[0]]
                print(
                    f"t={sim_s:7.0f} s  wall {time.perf_counter() - t0:7.0f} s  "
                    f"RSS {memory[-1]['rss_mib']:.1f} MiB  objects {memory[-1]['gc_objects']}  "
                    f"mass err {info['mass_rel_err']:.4f}  com err {info['com_err_m']:.4f} m  "
                    f"track {env.sim.tracking_error()[0]:.4f} m  checks ok "
                    f"{n_checks - len(failures)}/{n_checks}",
                    flush=True,
                )
        if not env.agents:
            reason = infos[env.possible_agents[0]]["termination_reason"]
            break
    wall = time.perf_counter() - t0
    gc.collect()
    memory.append(
        {
            "step": step,
            "sim_s": step * env.sim.dt_s,
            "rss_mib": rss_mib(),
            "gc_objects": len(gc.get_objects()),
        }
    )
    completed = step == n_steps and reason is None
    # RSS after the warm-up (the first progress sample) against the end: the steady-state growth.
    rss_warm = memory[1]["rss_mib"] if len(memory) > 2 else memory[0]["rss_mib"]
    summary = {
        "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "steps": step,
        "sim_s": step * env.sim.dt_s,
        "completed": completed,
        "termination_reason": reason,
        "wall_s": wall,
        "ms_per_step": 1e3 * wall / max(step, 1),
        "checks": n_checks,
        "failed_checks": len(failures),
        "worst": worst,
        "max_buffer_sizes": max_sizes,
        "buffer_bounds": buffer_bounds(env),
        "memory": memory,
        "rss_start_mib": memory[0]["rss_mib"],
        "rss_after_warmup_mib": rss_warm,
        "rss_end_mib": memory[-1]["rss_mib"],
        "heap_growth": heap,
        "max_tracking_error_m": track_max,
        "final": {
            a: {
                "mass_rel_err": infos[a].get("mass_rel_err"),
                "com_err_m": infos[a].get("com_err_m"),
                "principal_rel_err": np.asarray(infos[a].get("principal_rel_err")).tolist(),
                "estimator": infos[a].get("estimator"),
            }
            for a in env.possible_agents
        },
        "failures": failures[:10],
    }
    print()
    print(f"completed: {completed} ({step} steps, {summary['sim_s']:.0f} s simulated)")
    print(f"termination: {reason}")
    print(f"wall time: {wall:.0f} s ({summary['ms_per_step']:.2f} ms per step)")
    print(f"checks: {n_checks - len(failures)}/{n_checks} passed")
    print(
        f"  UKF P: exactly symmetric, smallest eigenvalue over the run {worst['P_min_eig']:.3e}, "
        f"largest condition number {worst['P_cond']:.3e}"
    )
    print(f"  params_cov: smallest eigenvalue over the run {worst['params_cov_min_eig']:.3e}")
    print("  largest buffer sizes (bound): ", end="")
    print(", ".join(f"{k} {v} ({summary['buffer_bounds'][k]})" for k, v in max_sizes.items()))
    print(
        f"memory: RSS start {memory[0]['rss_mib']:.1f} MiB, after warm-up {rss_warm:.1f} MiB, "
        f"end {memory[-1]['rss_mib']:.1f} MiB (growth after warm-up "
        f"{memory[-1]['rss_mib'] - rss_warm:+.1f} MiB); Python objects "
        f"{memory[0]['gc_objects']} -> {memory[-1]['gc_objects']}"
    )
    # Live traced heap at the end of each window: comparable, both traced for 2 windows. The
    # growth within a window also counts long-lived pools (numpy scalars) that were allocated
    # before tracing began and are replaced by traced ones: it is not by itself a leak.
    for name, h in heap.items():
        print(
            f"  traced heap ({name} window, {h['steps']} steps): live {h['traced_end_bytes']} "
            f"bytes at its end, {h['growth_bytes']:+d} bytes within it"
        )
    print(f"max cargo tracking error: {track_max:.4f} m")
    for a, f in summary["final"].items():
        print(f"  {a}: mass err {f['mass_rel_err']:.4f}, com err {f['com_err_m']:.4f} m")
        print(f"    counters {f['estimator']}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2, default=float))
        print(f"saved {args.json}")
    return 0 if completed and not failures else 1


if __name__ == "__main__":
    sys.exit(main())
