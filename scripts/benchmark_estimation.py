"""Estimation benchmark: the UKF next to batch least squares and the Cramer-Rao bound.

Runs scenarios x seeds through the environment (cooperative controller on the robots'
observations and live estimates), and for each case compares every robot's final estimate with
the truth, with batch weighted least squares on the very measurements robot 0's filter used, and
with the Cramer-Rao bound of those measurements. A second part compares the cargo tracking of the
controller with live estimates, with no cargo model and with the true model.

Each finished case is written at once (atomic rename) under ``--out-dir/cases/``; a rerun with
the same output directory skips finished cases, so an interrupted run resumes and leaves readable
results. The summary is ``results.json``, ``results.md`` (tables) and plots.

Cases run on this machine in a process pool (``--backend local --workers N``, the default) or as
Ray tasks on a cluster (``--backend ray --ray-address HOST:PORT``, default ``$RAY_ADDRESS``, else a
new local Ray instance; needs the ray extra, ``bash scripts/setup.sh --dev``, and astrocargo
installed on every node). Each case depends only on its seed, so both backends give the same
numbers; a case whose Ray worker dies runs again.

    .venv/bin/python scripts/benchmark_estimation.py                         # the standard suite
    .venv/bin/python scripts/benchmark_estimation.py --seeds 2 --duration 30  # a quick look
    .venv/bin/python scripts/benchmark_estimation.py --suite sweep --seeds 40 --duration 30 \\
        --backend ray --ray-address HEAD:6379                      # Monte Carlo over cargos
    .venv/bin/python scripts/benchmark_estimation.py --robots 2 --duration 90 --seed 3 \\
        --noise nominal --trajectory figure8_tumble --cargo-mass 5 --cargo-com 0.02,-0.03,0.04 \\
        --cargo-inertia 0.07,0.10,0.11,0.005,0,-0.004 --comm-latency 0.1 --comm-drop 0.2 \\
        --out case.json                                            # one custom case
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
# One BLAS thread per case: the matrices are tiny, and with several cases at once (pool workers,
# Ray tasks) more threads only contend for the cores (measured: 2 cases at once on 2 cores took
# 15-21 s each with OpenBLAS's default threads, 7-9 s with one). Ray's workers get one already.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling cli.py, ray_backend.py
from cli import (  # noqa: E402
    Formatter,
    VectorAction,
    check_trajectory,
    join_vector_values,
    nonnegative_float,
    nonnegative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
    trajectory,
)
from ray_backend import import_ray, ray_connection  # noqa: E402

from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402

# Default cargo: 5 kg, off-centre, full inertia tensor (cargo frame, about the centre of mass).
CARGO_MASS = 5.0
CARGO_COM = (0.02, -0.03, 0.04)
CARGO_INERTIA = (0.07, 0.10, 0.11, 0.005, 0.0, -0.004)
MASS_TOL = 0.02
CONTROL_HZ = 62.5
# Shortest analysed case: the estimators make no update in their first 4 s (warm-up), and batch
# least squares and the Cramer-Rao bound need recorded updates; twice the warm-up leaves 4 s.
MIN_DURATION_S = 8.0
VECTOR_OPTIONS = {"--cargo-com": 3, "--cargo-inertia": 6}
# Time to certainty: when the 2-sigma spread of each parameter group reaches its target (mass
# relative, centre of mass norm m, worst principal moment relative), sampled every second.
CERTAINTY_TARGETS = {"mass_rel": 0.01, "com_m": 0.005, "principal_rel": 0.05}
CERTAINTY_SIGMAS = 2.0
CERTAINTY_EVERY_S = 1.0
# The rows of the time-to-certainty table: (trajectory, robots) -> scenario name.
CERTAINTY_TRAJECTORIES = ("excite", "figure8_tumble", "figure8_yaw")
CERTAINTY_ROBOTS = (1, 2, 3)
BACKENDS = ("local", "ray")
# A Ray task whose worker process or node dies is run again up to this many times; an exception
# raised by the case itself is not retried (it would fail the same way).
RAY_MAX_RETRIES = 3
OUT_DIR = "out/benchmark_estimation"
CUSTOM_CASE_OUT = f"{OUT_DIR}/custom_case.json"  # under out/, which git ignores


@dataclass(frozen=True)
class Case:
    name: str
    robots: int
    trajectory: str
    seed: int
    duration: float = 90.0
    noise: str = "nominal"
    pan: bool = True
    fast: bool = False
    comm_latency: float = 0.0
    comm_drop: float = 0.0
    cargo_mass: float = CARGO_MASS
    cargo_com: tuple = CARGO_COM
    cargo_inertia: tuple | None = CARGO_INERTIA  # None: the uniform bag of that mass
    cargo_model: str = "estimate"
    analyse: bool = True  # False: control comparison only
    # "estimator_kwargs": more CargoEstimator args; "flush": False leaves a lagged estimator's
    # buffered tail unfed (``motion_lag_s``; default True)
    extra: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{self.name}__seed{self.seed}"


def smoke_cases(duration: float) -> list[Case]:
    """Three short cases (tests and a quick check of the pipeline)."""
    return [
        Case(
            "smoke: 1 robot",
            robots=1,
            trajectory="figure8_tumble",
            seed=s,
            duration=duration,
            noise="ideal",
        )
        for s in range(2)
    ] + [
        Case(
            "control: smoke, none",
            robots=1,
            trajectory="figure8_yaw",
            seed=0,
            duration=duration,
            noise="ideal",
            cargo_model="none",
            analyse=False,
        )
    ]


def sweep_cases(seeds: int, duration: float) -> list[Case]:
    """Monte Carlo over cargos: one case per seed, 2 robots on the tumbling figure-eight with
    nominal noise, the cargo's mass (2-10 kg) and centre of mass (+-3 cm per axis) drawn from the
    seed, inertia that of the uniform bag of that mass."""
    cases = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        mass = round(float(rng.uniform(2.0, 10.0)), 3)
        com = tuple(round(float(x), 4) for x in rng.uniform(-0.03, 0.03, 3))
        cases.append(
            Case(
                "sweep: 2 robots, tumble, random cargo",
                robots=2,
                trajectory="figure8_tumble",
                seed=seed,
                duration=duration,
                cargo_mass=mass,
                cargo_com=com,
                cargo_inertia=None,
            )
        )
    return cases


def standard_cases(seeds: int, duration: float) -> list[Case]:
    cases = []
    # One robot cannot follow figure8_tumble within its propulsion limits (measured: 8.6 deg mean
    # attitude error, then a wall contact), so the single-robot scenarios fly the paper's
    # figure8_yaw; the multi-robot ones fly the tumble (and 2 robots the yaw too).
    # Time to certainty compares excite, tumble and yaw at 1, 2 and 3 robots (certainty_name);
    # a team size without an excite design reports "no design".
    scenarios = [
        ("yaw: 1 robot, fixed arm", "figure8_yaw", dict(robots=1, pan=False)),
        ("yaw: 1 robot, pan ramp", "figure8_yaw", dict(robots=1)),
        ("yaw: 2 robots", "figure8_yaw", dict(robots=2)),
        ("yaw: 3 robots", "figure8_yaw", dict(robots=3)),
        ("tumble: 1 robot", "figure8_tumble", dict(robots=1)),
        ("tumble: 2 robots", "figure8_tumble", dict(robots=2)),
        ("tumble: 3 robots", "figure8_tumble", dict(robots=3)),
        ("excite: 1 robot", "excite", dict(robots=1)),
        ("excite: 2 robots", "excite", dict(robots=2)),
        ("excite: 3 robots", "excite", dict(robots=3)),
        (
            "tumble: 2 robots, 0.1 s latency, 20 % drop",
            "figure8_tumble",
            dict(robots=2, comm_latency=0.1, comm_drop=0.2),
        ),
    ]
    for seed in range(seeds):
        for name, traj, kw in scenarios:
            cases.append(Case(name, trajectory=traj, seed=seed, duration=duration, **kw))
    for traj, fast in (("figure8_yaw", False), ("figure8_tumble", False), ("figure8_yaw", True)):
        for model in ("estimate", "none", "truth"):
            label = f"control: {traj}{' fast' if fast else ''}, {model}"
            cases.append(
                Case(
                    label,
                    robots=2,
                    trajectory=traj,
                    seed=0,
                    duration=duration,
                    fast=fast,
                    cargo_model=model,
                    analyse=model == "estimate",
                )
            )
    return cases


def certainty_cases(seeds: int, duration: float) -> list[Case]:
    """The time-to-certainty scenarios of the standard suite only: excite, figure8_tumble and
    figure8_yaw at 1, 2 and 3 robots."""
    names = {certainty_name(t, n) for t in CERTAINTY_TRAJECTORIES for n in CERTAINTY_ROBOTS}
    return [c for c in standard_cases(seeds, duration) if c.name in names]


def certainty_name(trajectory: str, robots: int) -> str:
    """The standard scenario of the time-to-certainty row (trajectory, robots)."""
    short = {"excite": "excite", "figure8_tumble": "tumble", "figure8_yaw": "yaw"}[trajectory]
    suffix = ", pan ramp" if trajectory == "figure8_yaw" and robots == 1 else ""
    return f"{short}: {robots} robot{'s' if robots > 1 else ''}{suffix}"


# ------------------------------------------------------------------------------- certainty
def group_spreads(pi: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> dict:
    """1-sigma spreads of the parameter groups from the covariance ``cov`` of pi (grasp frame)
    at ``pi`` (``derived_covariance``), relative to ``truth``'s mass and principal moments:
    mass (relative), centre of mass (norm of the per-axis spreads, m), principal moments
    (relative, ascending)."""
    from astrocargo.estimator.baselines import derived_covariance
    from astrocargo.estimator.inertia import mass_com_inertia_from_params, principal_moments

    std = np.sqrt(np.maximum(np.diag(derived_covariance(pi, cov)), 0.0))
    moments = principal_moments(mass_com_inertia_from_params(truth)[2])
    return {
        "mass_rel": float(std[0] / truth[0]),
        "com_m": float(np.linalg.norm(std[1:4])),
        "principal_rel": [float(x) for x in std[4:7] / moments],
    }


def bound_spreads(log: list, n_rows: int, truth: np.ndarray) -> dict:
    """``group_spreads`` of the Cramer-Rao bound of the first ``n_rows`` updates of ``log`` (an
    estimator's record); infinite while a group is not observable yet."""
    from astrocargo.estimator.baselines import Recording, crlb

    inf = {"mass_rel": np.inf, "com_m": np.inf, "principal_rel": [np.inf] * 3}
    if n_rows < 2:
        return inf
    bound = crlb(Recording.from_log(log[:n_rows]), truth)
    if bound["unobservable"]:
        return inf
    return group_spreads(truth, bound["cov"], truth)


def time_to_certainty(times: list[float], spreads: list[dict]) -> dict:
    """Per group, the first sample time from which CERTAINTY_SIGMAS times the spread (the worst
    principal moment) stays at or below its CERTAINTY_TARGETS to the end; None if never."""
    out = {}
    for key, target in CERTAINTY_TARGETS.items():
        values = np.array([np.max(s[key]) for s in spreads]) * CERTAINTY_SIGMAS
        above = np.nonzero(~(values <= target))[0]
        first = 0 if not len(above) else above[-1] + 1
        out[key] = None if first >= len(times) else float(times[first])
    return out


# ------------------------------------------------------------------------------- one case
def run_case(case: Case) -> dict:
    """Simulate one case and analyse it (runs in a worker process)."""
    from astrocargo.agents.controllers import ObservationController
    from astrocargo.agents.excitation import EXCITE, has_design
    from astrocargo.agents.trajectories import Trajectory
    from astrocargo.envs import astrobee_cargo_v0
    from astrocargo.estimator.baselines import (
        PARAM_NAMES,
        Recording,
        batch_wls,
        convergence_time,
        crlb,
        fisher_information,
        unrevealed_directions,
    )
    from astrocargo.estimator.fused_motion import flush_team
    from astrocargo.estimator.inertia import (
        com_error_m,
        mass_com_inertia_from_params,
        mass_rel_error,
        principal_moments,
        principal_rel_errors,
        project_physical,
    )
    from astrocargo.estimator.ukf import (
        LOG_CHOLESKY_PRIOR_STD,
        LOG_CHOLESKY_PROCESS_STD,
        LogCholeskyUKF,
    )

    start = time.perf_counter()
    if case.trajectory == EXCITE and not has_design(case.robots):
        # The designer finds no flyable design for this team (none is shipped): a row that
        # says so, rather than a design on the fly that fails after minutes.
        return {"case": asdict(case), "wall_s": 0.0, "no_design": True}
    env = astrobee_cargo_v0.parallel_env(
        n_robots=case.robots,
        trajectory=case.trajectory,
        fast=case.fast,
        noise=case.noise,
        cargo_mass_kg=case.cargo_mass,
        cargo_com_m=case.cargo_com,
        cargo_inertia=case.cargo_inertia,
        comm_latency=case.comm_latency,
        comm_drop=case.comm_drop,
        max_cycles=int(round(case.duration * CONTROL_HZ)),
        estimator_kwargs={"record": case.analyse, **case.extra.get("estimator_kwargs", {})},
    )
    if not case.pan:
        sim = env.sim
        sim.trajectory = Trajectory(case.trajectory, fast=case.fast, pan_ramp=False)
    obs, _ = env.reset(seed=case.seed)
    sim = env.sim
    controller = ObservationController.for_env(env, case.cargo_model)
    times, mass_est, track, saturated, shortfall = [], [], [], 0, 0.0
    infos = {}
    # Every CERTAINTY_EVERY_S: time, robot 0's recorded updates, its filter's group spreads.
    sample_t, sample_rows, filter_spreads = [], [], []
    truth0 = sim.true_params_grasp[0]
    while env.agents:
        actions, _ = controller.predict(obs)
        obs, _, _, _, infos = env.step(actions)
        # A robot-step is saturated when the env could not deliver its whole thrust request.
        sat = [info["saturated"] for info in infos.values()]
        saturated += sum(x > 0 for x in sat)
        shortfall += sum(sat)
        times.append(float(sim.data.time))
        mass_est.append([m[0] for m in sim.est_mean])
        track.append(sim.tracking_error())
        if case.analyse and len(times) % int(round(CERTAINTY_EVERY_S * CONTROL_HZ)) == 0:
            est0 = sim.estimators[0]
            sample_t.append(times[-1])
            sample_rows.append(len(est0.log))
            filter_spreads.append(group_spreads(est0.params_mean(), est0.params_cov(), truth0))
    if case.extra.get("flush", True) and any(e.motion_lag_steps for e in sim.estimators):
        # Estimators fed a lag late (``motion_lag_s``): the buffered tail, smoothed on all the
        # data, so that the estimate holds the whole flight (``fused_motion.flush_team``).
        flush_team(sim.estimators)
    times, mass_est, track = np.asarray(times), np.asarray(mass_est), np.asarray(track)
    skip = len(track) // 6  # tracking statistics after the start-up
    result = {
        "case": asdict(case),
        "wall_s": time.perf_counter() - start,
        "sim_s": float(times[-1]),
        "termination_reason": next(iter(infos.values())).get("termination_reason"),
        "tracking": {
            "mean_pos_err_m": float(track[skip:, 0].mean()),
            "max_pos_err_m": float(track[:, 0].max()),
            "mean_att_err_rad": float(track[skip:, 1].mean()),
            "saturated_fraction": float(saturated / (len(track) * case.robots)),
            "mean_saturated": float(shortfall / (len(track) * case.robots)),
            "wall_contact": next(iter(infos.values())).get("termination_reason") == "wall_contact",
        },
    }
    if not case.analyse:
        env.close()
        return result
    agents = {}
    # A fresh estimator of robot 0: the prior every filter starts from.
    prior = type(sim.estimators[0])(sim.robots[0], 0, [], sim.dt_s)
    prior_std = prior.physical_estimate()[1][4:7]
    for i, agent in enumerate(env.possible_agents):
        est = sim.estimators[i]
        truth = sim.true_params_grasp[i]
        mean = est.params_mean()
        cov = est.params_cov()
        err = mean - truth
        agents[agent] = {
            "mass_rel_err": float(mass_rel_error(mean, truth)),
            "com_err_m": float(com_error_m(mean, truth)),
            "principal_rel_err": [float(x) for x in principal_rel_errors(mean, truth)],
            "mass_convergence_s": convergence_time(
                times, np.abs(mass_est[:, i] - truth[0]) / truth[0], MASS_TOL
            ),
            "nees": float(err @ np.linalg.solve(cov, err)),
            # Reported spread of the moments of inertia (grasp axes) relative to the prior's:
            # near 1 for what the motion cannot reveal.
            "inertia_std_rel_prior": [
                float(x) for x in est.physical_estimate()[1][4:7] / prior_std
            ],
            "counters": est.counters,
        }
    result["agents"] = agents
    # Baselines on robot 0's own measurements.
    est0 = sim.estimators[0]
    truth0 = sim.true_params_grasp[0]
    prior_params0 = prior.params_mean()
    rec = Recording.from_log(est0.log)
    wls, _ = batch_wls(rec)
    wls = project_physical(wls)
    result["batch_ls"] = {
        "mass_rel_err": float(mass_rel_error(wls, truth0)),
        "com_err_m": float(com_error_m(wls, truth0)),
        "principal_rel_err": [float(x) for x in principal_rel_errors(wls, truth0)],
    }
    # The same measurements through the log-Cholesky-state UKF (the design first built, replaced
    # by the standard-parameter filter: docs/design.md and estimator/ukf.py say why).
    lc = LogCholeskyUKF(prior_params0, LOG_CHOLESKY_PRIOR_STD, LOG_CHOLESKY_PROCESS_STD)
    for z, a, b, r in est0.log:
        lc.predict()
        lc.update_linear(z, a, b, r)
    lc_mean = lc.params_mean()
    lc_err = lc_mean - truth0
    result["log_cholesky_ukf"] = {
        "mass_rel_err": float(mass_rel_error(lc_mean, truth0)),
        "com_err_m": float(com_error_m(lc_mean, truth0)),
        "principal_rel_err": [float(x) for x in principal_rel_errors(lc_mean, truth0)],
        "nees": float(lc_err @ np.linalg.solve(lc.params_cov(), lc_err)),
    }
    bound = crlb(rec, truth0)
    moments = principal_moments(mass_com_inertia_from_params(truth0)[2])
    result["crlb"] = {
        "mass_rel_err": bound["std_mass"] / truth0[0],
        "com_err_m": float(np.linalg.norm(bound["std_com"])),
        "principal_rel_err": [float(x) for x in bound["std_principal"] / moments],
    }
    # What this trajectory cannot reveal: functionals with < 1 % of the prior's information.
    unseen = unrevealed_directions(fisher_information(rec), prior.params_cov())
    touched = set()
    for u in unseen:
        touched.update(PARAM_NAMES[k] for k in np.nonzero(np.abs(u) > 0.3 * np.abs(u).max())[0])
    result["unrevealed"] = {"count": len(unseen), "parameters": sorted(touched)}
    bounds = [bound_spreads(est0.log, n, truth0) for n in sample_rows]
    result["certainty"] = {
        "times_s": sample_t,
        "bound": bounds,
        "filter": filter_spreads,
        "time_to_bound_s": time_to_certainty(sample_t, bounds),
        "time_to_filter_s": time_to_certainty(sample_t, filter_spreads),
    }
    env.close()
    return result


# ------------------------------------------------------------------------------- storage
def atomic_write_json(path: Path, data: dict) -> None:
    """Write ``data`` to ``path`` so that a reader never sees a partial file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=2, default=_json_default)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _json_default(x):
    if isinstance(x, np.integer | np.floating):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def case_path(out_dir: Path, case: Case) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in case.key)
    return out_dir / "cases" / f"{safe}.json"


def run_all(
    cases: list[Case],
    out_dir: Path,
    workers: int,
    backend: str = "local",
    ray_address: str | None = None,
) -> list[dict]:
    """Run the cases not already finished under ``out_dir``; return every case's result.

    ``backend`` "local": a pool of ``workers`` processes on this machine (in this process if
    ``workers`` <= 1); "ray": one Ray task per case on the cluster at ``ray_address`` (None: a new
    local instance; an existing connection of this process is used as it is). Each result is
    written as soon as its case finishes."""
    from tqdm import tqdm

    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    done, todo = {}, []
    for case in cases:
        path = case_path(out_dir, case)
        if path.exists():
            try:
                done[case.key] = json.loads(path.read_text())
                continue
            except json.JSONDecodeError:
                pass  # a torn file from another writer: run the case again
        todo.append(case)
    if done:
        print(f"resuming: {len(done)} finished cases kept, {len(todo)} to run")
    if todo:
        if backend == "ray":
            finished = _finished_on_ray(todo, ray_address)
        else:
            finished = _finished_in_pool(todo, workers)
        with tqdm(total=len(todo), desc="cases", unit="case") as bar:
            for case, result in finished:
                done[case.key] = _finish(case, result, out_dir)
                bar.update()
    return [done[c.key] for c in cases]


def _finished_in_pool(cases: list[Case], workers: int) -> Iterator[tuple[Case, dict]]:
    """(case, result) pairs in the order the cases finish, on this machine."""
    if workers <= 1:
        for case in cases:
            yield case, run_case(case)
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(run_case, c): c for c in cases}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def _finished_on_ray(cases: list[Case], address: str | None) -> Iterator[tuple[Case, dict]]:
    """(case, result) pairs in the order the cases finish, one Ray task per case."""
    ray = import_ray()
    with ray_connection(ray, address):
        module = sys.modules[run_case.__module__]
        if module.__name__ != "__main__":
            # Imported (tests, notebooks): ship this script's code to the workers, which need
            # astrocargo installed but not this file on their path.
            ray.cloudpickle.register_pickle_by_value(module)
        task = ray.remote(num_cpus=1, max_retries=RAY_MAX_RETRIES)(run_case)
        case_of = {task.remote(case): case for case in cases}
        pending = list(case_of)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                yield case_of.pop(ref), ray.get(ref)


def _finish(case: Case, result: dict, out_dir: Path) -> dict:
    atomic_write_json(case_path(out_dir, case), result)
    return result


# ------------------------------------------------------------------------------- summary
def _fmt_pct(x):
    return "n/a" if x is None else f"{100 * x:.2f} %"


def summarise(results: list[dict]) -> dict:
    groups: dict[str, list[dict]] = {}
    for r in results:
        if "agents" in r and not r["case"]["name"].startswith("control"):
            groups.setdefault(r["case"]["name"], []).append(r)
    summary = {}
    for name, rs in groups.items():
        ukf = [a for r in rs for a in r["agents"].values()]
        conv = [a["mass_convergence_s"] for a in ukf]
        summary[name] = {
            "cases": len(rs),
            "ukf_mass_rel_err_max": max(a["mass_rel_err"] for a in ukf),
            "ukf_com_err_m_max": max(a["com_err_m"] for a in ukf),
            "ukf_principal_rel_err_max": np.max([a["principal_rel_err"] for a in ukf], 0).tolist(),
            "ukf_mass_convergence_s_max": None if None in conv else max(conv),
            "ukf_nees_mean": float(np.mean([a["nees"] for a in ukf])),
            "ukf_inertia_std_rel_prior_mean": np.mean(
                [a["inertia_std_rel_prior"] for a in ukf], 0
            ).tolist(),
            "log_cholesky_principal_rel_err_max": np.max(
                [r["log_cholesky_ukf"]["principal_rel_err"] for r in rs], 0
            ).tolist(),
            "log_cholesky_nees_mean": float(np.mean([r["log_cholesky_ukf"]["nees"] for r in rs])),
            "wls_mass_rel_err_max": max(r["batch_ls"]["mass_rel_err"] for r in rs),
            "wls_com_err_m_max": max(r["batch_ls"]["com_err_m"] for r in rs),
            "wls_principal_rel_err_max": np.max(
                [r["batch_ls"]["principal_rel_err"] for r in rs], 0
            ).tolist(),
            "crlb_mass_rel_std": float(np.mean([r["crlb"]["mass_rel_err"] for r in rs])),
            "crlb_com_std_m": float(np.mean([r["crlb"]["com_err_m"] for r in rs])),
            "crlb_principal_rel_std": np.mean(
                [r["crlb"]["principal_rel_err"] for r in rs], 0
            ).tolist(),
            # Principal moments the data cannot pin down: Cramer-Rao bound above 50 %.
            "unrevealed": [
                f"I{k + 1}"
                for k in range(3)
                if np.mean([r["crlb"]["principal_rel_err"][k] for r in rs]) > 0.5
            ],
            "termination": sorted({str(r["termination_reason"]) for r in rs}),
        }
    control = {}
    for r in results:
        name = r["case"]["name"]
        if name.startswith("control"):
            traj = name.split(": ", 1)[1].rsplit(", ", 1)[0]
            control.setdefault(traj, {})[r["case"]["cargo_model"]] = r["tracking"]
    return {"scenarios": summary, "control": control, "certainty": summarise_certainty(results)}


def _worst_time(values: list) -> float | None:
    """The latest of the seeds' times (None if any seed never gets there)."""
    return None if not values or None in values else max(values)


def _mean_curve(rs: list[dict], source: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    """Sample times and the seeds' mean of 2-sigma spreads (worst principal moment) of group
    ``key`` from ``source`` ("bound" or "filter"), over the samples every seed has."""
    n = min(len(r["certainty"]["times_s"]) for r in rs)
    t = np.asarray(rs[0]["certainty"]["times_s"][:n])
    vals = [[CERTAINTY_SIGMAS * np.max(s[key]) for s in r["certainty"][source][:n]] for r in rs]
    return t, np.mean(vals, axis=0)


def summarise_certainty(results: list[dict]) -> dict:
    """The time-to-certainty rows, (trajectory, robots) of CERTAINTY_TRAJECTORIES x
    CERTAINTY_ROBOTS present in ``results``: final 2-sigma bound and filter spreads (seeds'
    mean), times to certainty (the latest seed's), saturation, wall contacts, tracking; and per
    team size the time excite's bound needs to reach the tumble's final bound."""
    rows, reach = {}, {}
    for robots in CERTAINTY_ROBOTS:
        for traj in CERTAINTY_TRAJECTORIES:
            name = certainty_name(traj, robots)
            rs = [r for r in results if r["case"]["name"] == name]
            if not rs:
                continue
            key = f"{traj}, {robots}"
            if any(r.get("no_design") for r in rs):
                rows[key] = {"trajectory": traj, "robots": robots, "no_design": True}
                continue
            rs = [r for r in rs if "certainty" in r]
            if not rs:
                continue
            final = {
                src: {
                    k: float(
                        np.mean([CERTAINTY_SIGMAS * np.max(r["certainty"][src][-1][k]) for r in rs])
                    )  # fmt: skip
                    for k in CERTAINTY_TARGETS
                }
                for src in ("bound", "filter")
            }
            rows[key] = {
                "trajectory": traj,
                "robots": robots,
                "seeds": len(rs),
                "final_2sigma": final,
                "time_to_bound_s": {
                    k: _worst_time([r["certainty"]["time_to_bound_s"][k] for r in rs])
                    for k in CERTAINTY_TARGETS
                },
                "time_to_filter_s": {
                    k: _worst_time([r["certainty"]["time_to_filter_s"][k] for r in rs])
                    for k in CERTAINTY_TARGETS
                },
                "saturated_fraction": float(
                    np.mean([r["tracking"]["saturated_fraction"] for r in rs])
                ),
                "wall_contacts": int(sum(r["tracking"]["wall_contact"] for r in rs)),
                "mean_pos_err_m": float(np.mean([r["tracking"]["mean_pos_err_m"] for r in rs])),
                "sim_s": float(min(r["sim_s"] for r in rs)),
            }
        excite, tumble = (
            [
                r
                for r in results
                if r["case"]["name"] == certainty_name(traj, robots) and "certainty" in r
            ]
            for traj in ("excite", "figure8_tumble")
        )
        if excite and tumble:
            reach[robots] = {}
            for k in CERTAINTY_TARGETS:
                target = _mean_curve(tumble, "bound", k)[1][-1]
                t, curve = _mean_curve(excite, "bound", k)
                below = np.nonzero(curve <= target)[0]
                reach[robots][k] = float(t[below[0]]) if len(below) else None
    return {"rows": rows, "excite_reaches_tumble_s": reach}


def markdown(summary: dict) -> str:
    lines = [
        "## Estimation (max over seeds and robots; CRLB: mean 1-sigma bound of robot 0's data;",
        "principal moments sorted ascending, I1 <= I2 <= I3; NEES: mean over seeds and robots,",
        "10 for a consistent filter, one run's 95 % range 3.2 to 20.5; UKF / CRLB: the UKF's",
        "worst error over the bound for mass, CoM and the worst principal moment)",
        "",
        "| scenario | seeds | UKF mass | UKF CoM | UKF principal moments | mass conv. | NEES "
        "(10 dof) | UKF / CRLB | batch LS mass | batch LS CoM | batch LS principal | CRLB mass "
        "| CRLB CoM | CRLB principal | not revealed (CRLB > 50 %) | reported std / prior "
        "(I_xx, I_yy, I_zz) | log-Cholesky UKF principal, NEES |",
        "|---" * 17 + "|",
    ]
    for name, s in summary["scenarios"].items():
        pr = " / ".join(f"{100 * x:.1f}" for x in s["ukf_principal_rel_err_max"])
        wpr = " / ".join(f"{100 * x:.1f}" for x in s["wls_principal_rel_err_max"])
        cpr = " / ".join(f"{100 * x:.1f}" for x in s["crlb_principal_rel_std"])
        conv = s["ukf_mass_convergence_s_max"]
        ratio = " / ".join(
            f"{x:.1f}"
            for x in (
                s["ukf_mass_rel_err_max"] / s["crlb_mass_rel_std"],
                s["ukf_com_err_m_max"] / s["crlb_com_std_m"],
                max(
                    e / c
                    for e, c in zip(
                        s["ukf_principal_rel_err_max"], s["crlb_principal_rel_std"], strict=True
                    )
                ),
            )
        )
        spread = " / ".join(f"{x:.2f}" for x in s["ukf_inertia_std_rel_prior_mean"])
        lc = " / ".join(f"{100 * x:.1f}" for x in s["log_cholesky_principal_rel_err_max"])
        lines.append(
            f"| {name} | {s['cases']} | {_fmt_pct(s['ukf_mass_rel_err_max'])} | "
            f"{1e3 * s['ukf_com_err_m_max']:.1f} mm | {pr} % | "
            f"{'never' if conv is None else f'{conv:.1f} s'} | {s['ukf_nees_mean']:.1f} | "
            f"{ratio} | "
            f"{_fmt_pct(s['wls_mass_rel_err_max'])} | {1e3 * s['wls_com_err_m_max']:.1f} mm | "
            f"{wpr} % | {_fmt_pct(s['crlb_mass_rel_std'])} | {1e3 * s['crlb_com_std_m']:.1f} mm "
            f"| {cpr} % | {', '.join(s['unrevealed']) or '-'} | {spread} | "
            f"{lc} %, {s['log_cholesky_nees_mean']:.0f} |"
        )
    lines += [
        "",
        "## Cargo tracking by cargo model (mean position error after the first sixth)",
        "",
        "| trajectory | live estimate | no model | true model | estimate / truth | "
        "estimate / none | saturated (estimate) |",
        "|---|---|---|---|---|---|---|",
    ]
    for traj, models in summary["control"].items():
        if not {"estimate", "none", "truth"} <= set(models):
            continue
        e, n, t = (models[m]["mean_pos_err_m"] for m in ("estimate", "none", "truth"))
        lines.append(
            f"| {traj} | {100 * e:.2f} cm | {100 * n:.2f} cm | {100 * t:.2f} cm | {e / t:.2f} | "
            f"{e / n:.2f} | {100 * models['estimate']['saturated_fraction']:.1f} % |"
        )
    return "\n".join(lines) + "\n" + certainty_markdown(summary.get("certainty", {"rows": {}}))


def _fmt_time(x):
    return "never" if x is None else f"{x:.0f} s"


def certainty_markdown(cert: dict) -> str:
    """The time-to-certainty table and the excite-versus-tumble times."""
    if not cert["rows"]:
        return ""
    lines = [
        "",
        f"## Time to certainty ({CERTAINTY_SIGMAS:g} sigma: mass "
        f"{100 * CERTAINTY_TARGETS['mass_rel']:g} %, CoM {1e3 * CERTAINTY_TARGETS['com_m']:g} "
        f"mm, worst principal moment {100 * CERTAINTY_TARGETS['principal_rel']:g} %; robot 0; "
        "bound: Cramer-Rao bound of the updates so far, filter: the UKF's reported spread; "
        "spreads at the end: mean over seeds, times: the latest seed's; saturated: robot-steps "
        "whose thrust request was clipped)",
        "",
        "| trajectory | robots | seeds | bound at end (mass / CoM / principal) | filter at end "
        "| time to certainty, bound | time to certainty, filter | saturated | wall contacts "
        "| tracking |",
        "|---" * 10 + "|",
    ]
    for row in cert["rows"].values():
        if row.get("no_design"):
            lines.append(
                f"| {row['trajectory']} | {row['robots']} | - | no design | - | - | - | - | - | - |"
            )
            continue
        fin = row["final_2sigma"]

        def spreads(src, fin=fin):
            f = fin[src]
            return (
                f"{100 * f['mass_rel']:.2f} % / {1e3 * f['com_m']:.1f} mm / "
                f"{100 * f['principal_rel']:.1f} %"
            )

        def times(key, row=row):
            return " / ".join(_fmt_time(row[key][k]) for k in CERTAINTY_TARGETS)

        lines.append(
            f"| {row['trajectory']} | {row['robots']} | {row['seeds']} | {spreads('bound')} | "
            f"{spreads('filter')} | {times('time_to_bound_s')} | {times('time_to_filter_s')} | "
            f"{100 * row['saturated_fraction']:.1f} % | {row['wall_contacts']} | "
            f"{100 * row['mean_pos_err_m']:.2f} cm |"
        )
    for robots, reach in cert["excite_reaches_tumble_s"].items():
        lines.append(
            f"\nexcite, {robots} robot{'s' if robots > 1 else ''}: reaches figure8_tumble's final "
            f"bound (mass / CoM / principal) at "
            + " / ".join(_fmt_time(reach[k]) for k in CERTAINTY_TARGETS)
        )
    return "\n".join(lines) + "\n"


def plot_certainty(results: list[dict], path: Path) -> None:
    """2-sigma spreads over time per team size (rows) and parameter group (columns): the
    Cramer-Rao bound (solid) and the filter's reported spread (dashed), seeds' mean, one colour
    per trajectory, the target as a grey line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    teams = [
        n
        for n in CERTAINTY_ROBOTS
        if any(
            "certainty" in r and r["case"]["name"] == certainty_name(t, n)
            for r in results
            for t in CERTAINTY_TRAJECTORIES
        )
    ]
    if not teams:
        return
    fig, axes = plt.subplots(
        len(teams), 3, figsize=(14, 3.2 * len(teams)), squeeze=False, layout="constrained"
    )
    scale = {"mass_rel": 100, "com_m": 1e3, "principal_rel": 100}
    titles = {"mass_rel": "mass [%]", "com_m": "CoM [mm]", "principal_rel": "worst principal [%]"}
    colours = dict(zip(CERTAINTY_TRAJECTORIES, ("tab:red", "tab:blue", "tab:green"), strict=True))
    for row, n in zip(axes, teams, strict=True):
        for ax, key in zip(row, CERTAINTY_TARGETS, strict=True):
            for traj in CERTAINTY_TRAJECTORIES:
                rs = [
                    r
                    for r in results
                    if r["case"]["name"] == certainty_name(traj, n) and "certainty" in r
                ]
                if not rs:
                    continue
                for src, style in (("bound", "-"), ("filter", "--")):
                    t, curve = _mean_curve(rs, src, key)
                    ax.plot(
                        t, scale[key] * curve, style, color=colours[traj],
                        label=f"{traj} ({src})",
                    )  # fmt: skip
            ax.axhline(scale[key] * CERTAINTY_TARGETS[key], color="grey", lw=1)
            ax.set_yscale("log")
            ax.set_title(f"{n} robot{'s' if n > 1 else ''}: {titles[key]}, 2 sigma", fontsize=9)
            ax.set_xlabel("time [s]")
            ax.grid(alpha=0.3)
    legend = {}  # every trajectory's lines, whichever team flew it
    for ax in axes[:, 0]:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(label, handle)
    fig.legend(legend.values(), legend.keys(), fontsize=8, loc="outside lower center", ncols=3)
    fig.suptitle(
        "Time to certainty: Cramer-Rao bound (solid) and the UKF's reported spread (dashed)",
        fontsize=10,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_conditions(results: list[dict]) -> str:
    """One line stating how the analysed cases ran: seeds, duration, noise, cargo."""
    cases = [r["case"] for r in results if "agents" in r]
    seeds = sorted({c["seed"] for c in cases})
    durations = sorted({c["duration"] for c in cases})
    noises = sorted({c["noise"] for c in cases})
    masses = sorted({c["cargo_mass"] for c in cases})
    mass = f"{masses[0]:g} kg" if len(masses) == 1 else f"{masses[0]:g}-{masses[-1]:g} kg"
    return (
        f"{len(seeds)} seed{'s' if len(seeds) != 1 else ''} per scenario, "
        f"{' / '.join(f'{d:g}' for d in durations)} s simulated, {' / '.join(noises)} noise, "
        f"{mass} cargo; UKF: every robot's final estimate; batch LS and CRLB: robot 0's "
        f"measurements"
    )


def plot(results: list[dict], path: Path) -> None:
    """Final errors per scenario (one row each): every robot's UKF estimate, batch least squares
    and the Cramer-Rao bound of robot 0's measurements, on log axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    names = sorted(
        {
            r["case"]["name"]
            for r in results
            if "agents" in r and not r["case"]["name"].startswith("control")
        },
        reverse=True,  # top to bottom in alphabetical order
    )
    fig, axes = plt.subplots(
        1, 3, figsize=(15, 1.6 + 0.55 * len(names)), sharey=True, layout="constrained"
    )
    for k, name in enumerate(names):
        rs = [r for r in results if r["case"]["name"] == name]
        ukf = [a for r in rs for a in r["agents"].values()]
        for ax, key, scale in zip(
            axes, ("mass_rel_err", "com_err_m", "principal_rel_err"), (100, 1e3, 100), strict=True
        ):
            vals = [scale * np.max(a[key]) for a in ukf]
            wls = [scale * np.max(r["batch_ls"][key]) for r in rs]
            bound = [scale * np.max(r["crlb"][key]) for r in rs]
            ax.scatter(
                vals, [k] * len(vals), color="tab:blue", s=14, label="UKF" if k == 0 else None
            )
            ax.scatter(
                wls,
                [k - 0.2] * len(wls),
                color="tab:orange",
                s=14,
                label="batch LS" if k == 0 else None,
            )
            ax.scatter(
                bound,
                [k + 0.2] * len(bound),
                color="k",
                marker="|",
                s=80,
                label="CRLB (1 sigma)" if k == 0 else None,
            )
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for ax, title in zip(
        axes, ("mass error [%]", "CoM error [mm]", "worst principal moment error [%]"), strict=True
    ):
        ax.set_xlabel(title)
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(plain)
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(alpha=0.3)
    axes[0].set_yticks(range(len(names)), names, fontsize=9)
    axes[0].set_ylim(-0.6, len(names) - 0.4)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncols=len(labels))
    fig.suptitle(f"Final estimation errors per scenario - {run_conditions(results)}", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    p.add_argument("--out-dir", default=OUT_DIR)
    p.add_argument(
        "--seeds", type=positive_int, default=5, help="seeds per scenario (standard suite)"
    )
    p.add_argument(
        "--workers", type=positive_int, default=2, help="processes for the cases (--backend local)"
    )
    p.add_argument(
        "--duration",
        type=positive_float,
        default=90.0,
        help=f"simulated seconds per case, at least {MIN_DURATION_S:g}",
    )
    p.add_argument(
        "--suite",
        choices=("standard", "smoke", "sweep", "certainty"),
        default="standard",
        help="sweep: --seeds cases, each a random cargo; certainty: the standard suite's "
        "time-to-certainty scenarios only (excite, tumble, yaw at 1, 2, 3 robots)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="local", help="where cases run")
    p.add_argument(
        "--ray-address",
        default=os.environ.get("RAY_ADDRESS"),
        help="Ray cluster (HOST:PORT) for --backend ray, default $RAY_ADDRESS; none: a new local "
        "Ray instance",
    )
    # One custom case (these exact flags); with --robots the standard suite is not run.
    p.add_argument("--robots", type=int, help=f"1..{MAX_ROBOTS}: run one custom case")
    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--noise", choices=sorted(NOISE_PROFILES), default="nominal")
    p.add_argument(
        "--trajectory",
        type=trajectory,
        default="figure8_tumble",
        help="figure8_yaw, figure8_tumble, hover, excite (the team's designed excitation) or a "
        "design JSON file",
    )
    p.add_argument("--cargo-mass", type=positive_float, default=CARGO_MASS, help="kg")
    p.add_argument(
        "--cargo-com",
        action=VectorAction,
        size=3,
        default=CARGO_COM,
        help="m, cargo frame: 3 numbers, comma-separated (--cargo-com=-0.045,0.012,-0.03) or "
        "separated by spaces (--cargo-com -0.045 0.012 -0.03)",
    )
    p.add_argument(
        "--cargo-inertia",
        action=VectorAction,
        size=6,
        default=CARGO_INERTIA,
        help="kg m^2 about the centre of mass: Ixx,Iyy,Izz,Ixy,Ixz,Iyz, written as --cargo-com",
    )
    p.add_argument("--comm-latency", type=nonnegative_float, default=0.0, help="seconds")
    p.add_argument("--comm-drop", type=nonnegative_float, default=0.0, help="probability, < 1")
    p.add_argument(
        "--out",
        default=CUSTOM_CASE_OUT,
        help="JSON file of the custom case (--robots)",
    )
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked, with its output folder created: every error is the parser's,
    before any case runs. A comma-separated vector may start with a minus sign after a space
    (``--cargo-com -0.045,0.012,-0.03``)."""
    p = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = p.parse_args(join_vector_values(argv, list(VECTOR_OPTIONS)))
    if args.duration < MIN_DURATION_S:
        p.error(
            f"--duration must be at least {MIN_DURATION_S:g} s (the estimators' 4 s warm-up and "
            f"time to record updates), got {args.duration:g}"
        )
    if args.robots is not None:
        if not 1 <= args.robots <= MAX_ROBOTS:
            p.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
        check_trajectory(p, args.trajectory, args.robots)
        if not args.comm_drop < 1:
            p.error(f"--comm-drop must be a probability below 1, got {args.comm_drop:g}")
        output_file(p, Path(args.out), "--out")
    else:
        output_dir(p, Path(args.out_dir), "--out-dir")
    if args.backend == "ray":
        try:
            import_ray()
        except ImportError as err:
            p.error(str(err))
    return args


def suite_cases(args: argparse.Namespace) -> list[Case]:
    """The cases of ``--suite``."""
    if args.suite == "smoke":
        return smoke_cases(args.duration)
    if args.suite == "sweep":
        return sweep_cases(args.seeds, args.duration)
    if args.suite == "certainty":
        return certainty_cases(args.seeds, args.duration)
    return standard_cases(args.seeds, args.duration)


def seed_list(cases: list[Case]) -> str:
    """The seeds the cases use, as "0..4" when consecutive."""
    seeds = sorted({c.seed for c in cases})
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"{seeds[0]}..{seeds[-1]}"
    return ", ".join(map(str, seeds))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    p = build_parser()

    if args.robots is not None:
        case = Case(
            "custom",
            robots=args.robots,
            trajectory=args.trajectory,
            seed=args.seed,
            duration=args.duration,
            noise=args.noise,
            cargo_mass=args.cargo_mass,
            cargo_com=args.cargo_com,
            cargo_inertia=args.cargo_inertia,
            comm_latency=args.comm_latency,
            comm_drop=args.comm_drop,
        )
        print(f"seed {case.seed}")
        try:
            result = run_case(case)
        except ValueError as err:  # invalid physical values or env arguments
            p.error(str(err))
        out = Path(args.out)
        atomic_write_json(out, result)
        for agent, a in result["agents"].items():
            print(
                f"{agent}: mass {100 * a['mass_rel_err']:.2f} %, CoM "
                f"{1e3 * a['com_err_m']:.1f} mm, principal "
                f"{[round(100 * x, 1) for x in a['principal_rel_err']]} %, mass converged at "
                f"{a['mass_convergence_s']} s"
            )
        print(f"batch LS: {result['batch_ls']}\nCRLB: {result['crlb']}\nwritten {out}")
        return 0

    out_dir = Path(args.out_dir)
    cases = suite_cases(args)
    where = (
        f"{args.workers} local processes"
        if args.backend == "local"
        else f"Ray at {args.ray_address or 'a new local instance'}"
    )
    print(f"seeds {seed_list(cases)}; {len(cases)} cases on {where}; output {out_dir}")
    start = time.perf_counter()
    results = run_all(cases, out_dir, args.workers, args.backend, args.ray_address)
    print(f"cases finished in {time.perf_counter() - start:.1f} s")
    summary = summarise(results)
    atomic_write_json(out_dir / "results.json", {"summary": summary, "cases": results})
    table = markdown(summary)
    (out_dir / "results.md").write_text(table)
    plot(results, out_dir / "errors.png")
    plot_certainty(results, out_dir / "certainty.png")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
