"""Score policies on the same seeded episodes of the Astrobee cargo env.

A policy is a run folder of scripts/train.py (``model.zip``, ``vecnormalize.pkl``,
``config.json``), ``scripted`` (``ObservationController`` with ``--cargo-model``; ``scripted:none``,
``scripted:truth`` pick the cargo model, ``scripted@excite`` flies another trajectory) or ``zero``
(all actions zero). Episode k of every policy is reset with seed ``--seed + k``: the same cargo
and the same noise draws. With ``--mass-bins`` each bin [low, high) of cargo masses gets its own
``--episodes`` episodes (the mass drawn uniformly within the bin, seeds ``--seed + k`` again).
Every episode runs at the env's control rate: a trained policy decides every ``action_repeat``
steps (its ``DecisionEnv``) and, if residual, its action is added to the action of its scripted
base controller (no cargo model or the live estimate) at every step, exactly as in training. The
estimators always run (they do not change the physics), so their errors are reported whatever the
policy observes.

Per policy (and bin) it prints mean and spread (standard deviation over episodes) of the
return (mean over robots), the cargo tracking error (true pose, mean over the episode and at
its end), the estimators' errors at the end (mean over robots), the time after which the mass
error stays within 5 %, the saturation share (``infos["saturated"]``, mean over steps and
robots) and the episodes ended by wall contact; ``--bound`` adds robot 0's principal-moment
bound at the end (Cramer-Rao bound of its updates, relative, and the filter's own spread);
``--correction`` adds how much the live estimate changes the scripted thrust (``ModelCorrection``:
the residual a policy on the no-model controller would have to learn).
``--ablation`` groups run folders into arms (same configuration but the seed) and prints, per
mass bin, each arm's mean and spread over seeds and whether the difference between arms that
differ only in observing the estimates exceeds that spread. ``--json`` writes everything.

    .venv/bin/python scripts/evaluate.py --policy runs/ppo_est runs/ppo_noest zero scripted \\
        --episodes 10 --json runs/eval.json
    MUJOCO_GL=egl .venv/bin/python scripts/evaluate.py --policy runs/ppo_est --video out/videos

The task (robots, trajectory, episode length, noise, cargo) comes from the first run folder's
configuration, else from ``--task`` (``LEARNING_TASKS`` of ``astrocargo.envs.config``), and the
flags override it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")  # only used with --video

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py, eval_*.py
from cli import (  # noqa: E402
    Formatter,
    nonnegative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
)
from eval_policies import (  # noqa: E402
    DEFAULT_TASK,
    POLICY_HELP,
    TrainedPolicy,
    check_policy_spec,
    checkpoint_samples,
    make_policy,
)
from eval_report import (  # noqa: E402
    BOUND_METRICS,
    CORRECTION_METRICS,
    METRICS,
    ablation,
    plot_curves,
    print_ablation,
    print_table,
)

from astrocargo.agents.controllers import CARGO_MODELS  # noqa: E402
from astrocargo.agents.model_correction import ModelCorrection  # noqa: E402
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs import astrobee_cargo_v0  # noqa: E402
from astrocargo.envs.config import LEARNING_TASKS, REWARD_TERMS  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402

# Stable-Baselines3 and torch (astrocargo.envs.wrappers imports them) load after the command line
# is parsed: --help and argument errors answer at once.

MASS_CONV_TOL = 0.05  # mass_conv_s: the mass error stays within this (relative) from then on


# --------------------------------------------------------------------------- episodes


def run_episode(
    policy,
    env,
    seed: int,
    frames: list | None = None,
    every: int = 8,
    bound: bool = False,
    correction: bool = False,
) -> dict:
    """One seeded episode at the env's control rate; returns its metrics."""
    from astrocargo.estimator.baselines import convergence_time

    obs_dict, _ = env.reset(seed=seed)
    policy.reset(env)
    agents = env.possible_agents
    total, pos_errs, att_errs, times, mass_errs, saturated, step = 0.0, [], [], [], [], [], 0
    terms = dict.fromkeys(REWARD_TERMS, 0.0)
    model = ModelCorrection(env) if correction else None
    while env.agents:
        obs = np.stack([obs_dict[a] for a in agents])
        if model is not None:
            model.record(obs, times[-1] if times else 0.0)
        actions = policy.act(obs)
        obs_dict, rewards, _, _, infos = env.step(dict(zip(agents, actions, strict=True)))
        total += float(np.mean([rewards[a] for a in agents]))
        for term in REWARD_TERMS:
            terms[term] += float(np.mean([infos[a][f"reward_{term}"] for a in agents]))
        pos, att = env.sim.tracking_error()
        pos_errs.append(pos)
        att_errs.append(att)
        times.append(infos[agents[0]]["time_s"])
        mass_errs.append(float(np.mean([infos[a]["mass_rel_err"] for a in agents])))
        saturated.append(float(np.mean([infos[a]["saturated"] for a in agents])))
        if frames is not None and step % every == 0:
            frames.append(env.render())
        step += 1
    last = [infos[a] for a in agents]
    conv = convergence_time(np.array(times), np.array(mass_errs), MASS_CONV_TOL)
    row = {
        "seed": seed,
        "cargo_mass_kg": float(env.sim.world.cargo_params()[0]),
        "steps": step,
        "termination_reason": last[0]["termination_reason"],
        "return": total,
        "track_pos_m": float(np.mean(pos_errs)),
        "track_att_rad": float(np.mean(att_errs)),
        "final_pos_m": pos_errs[-1],
        "final_att_rad": att_errs[-1],
        "mass_rel_err": float(np.mean([i["mass_rel_err"] for i in last])),
        "com_err_m": float(np.mean([i["com_err_m"] for i in last])),
        "principal_rel_err": float(np.mean([np.mean(i["principal_rel_err"]) for i in last])),
        "mass_conv_s": float("nan") if conv is None else conv,
        "saturated": float(np.mean(saturated)),
        "wall_contact": float(last[0]["termination_reason"] == "wall_contact"),
        **{f"return_{term}": value for term, value in terms.items()},
    }
    if bound:
        row.update(principal_bounds(env.sim))
    if model is not None:
        row.update(model.metrics())
    return row


def principal_bounds(sim) -> dict[str, list[float]]:
    """Robot 0's principal-moment spreads at the end, relative to the true moments, ascending:
    the Cramer-Rao bound of its recorded updates (inf where not yet observable) and its
    filter's own spread (``benchmark_estimation.bound_spreads``, ``group_spreads``)."""
    from benchmark_estimation import bound_spreads, group_spreads

    est, truth = sim.estimators[0], sim.true_params_grasp[0]
    crlb = bound_spreads(est.log, len(est.log), truth)
    spread = group_spreads(est.params_mean(), est.params_cov(), truth)
    return {
        "bound_principal_rel": [float(x) for x in crlb["principal_rel"]],
        "filter_principal_rel": [float(x) for x in spread["principal_rel"]],
    }


def mass_bins(edges: list[float] | None, task: dict[str, Any]) -> list[tuple[float, float]]:
    """The (low, high) cargo mass ranges of the evaluation: the bins between ``edges``, or the
    task's own range (one bin)."""
    if edges:
        return list(zip(edges[:-1], edges[1:], strict=True))
    mass = task.get("cargo_mass_kg", 5.0)
    low, high = (mass, mass) if np.isscalar(mass) else mass
    return [(float(low), float(high))]


def bin_name(bounds: tuple[float, float]) -> str:
    low, high = bounds
    return f"{low:g} kg" if low == high else f"{low:g}-{high:g} kg"


def summarise(rows: list[dict]) -> dict:
    """Mean and standard deviation over episodes of every metric (nan-aware: mass_conv_s is nan
    in an episode where the mass error never stays within the tolerance)."""
    summary = {}
    extra = BOUND_METRICS + CORRECTION_METRICS
    keys = [k for k, _, _ in METRICS] + [k for k, _ in extra if k in rows[0]]
    keys += [f"return_{term}" for term in REWARD_TERMS]
    for key in keys:
        values = np.array([r[key] for r in rows], dtype=float)
        finite = values[np.isfinite(values)] if values.ndim == 1 else values
        summary[key] = {
            "mean": (np.mean(finite, axis=0) if len(finite) else np.full(1, np.nan)).tolist(),
            "std": (np.std(finite, axis=0) if len(finite) else np.full(1, np.nan)).tolist(),
        }
    summary["mass_conv_s"]["never"] = int(np.sum(np.isnan([r["mass_conv_s"] for r in rows])))
    return summary


def evaluate(
    policy,
    task: dict[str, Any],
    episodes: int,
    seed: int,
    video: Path | None,
    bins: list[tuple[float, float]] | None = None,
    bound: bool = False,
    correction: bool = False,
) -> dict:
    """Every episode of one policy (per mass bin), and the mean and standard deviation of each
    metric per bin and over all episodes (``bound``, ``correction``: see ``run_episode``; the
    correction only where the policy's env observes the estimates)."""
    correction = correction and policy.observe_estimates
    start = time.perf_counter()
    rows, per_bin = [], {}
    for bounds in bins or mass_bins(None, task):
        kwargs = {**task, "cargo_mass_kg": bounds if bounds[1] > bounds[0] else bounds[0]}
        if policy.trajectory:
            kwargs["trajectory"] = policy.trajectory
        env = astrobee_cargo_v0.parallel_env(
            **kwargs,
            observe_estimates=policy.observe_estimates,
            estimators=True,
            estimator_kwargs={"record": True} if bound else None,
            render_mode="rgb_array" if video else None,
        )
        bin_rows = []
        for k in range(episodes):
            frames = [] if video and k == 0 and not rows else None
            bin_rows.append(
                run_episode(policy, env, seed + k, frames, bound=bound, correction=correction)
            )
            if frames:
                video.mkdir(parents=True, exist_ok=True)
                safe = "".join(c if c.isalnum() else "_" for c in policy.name).strip("_")
                save_gif(frames, video / f"{safe}.gif", fps=env.metadata["render_fps"] / 8)
        env.close()
        for r in bin_rows:
            r["bin"] = bin_name(bounds)
        per_bin[bin_name(bounds)] = summarise(bin_rows)
        rows += bin_rows
    terminated = sum(r["termination_reason"] is not None for r in rows)
    return {
        "policy": policy.name,
        "observe_estimates": policy.observe_estimates,
        "config": getattr(policy, "config", None),
        "wall_s": time.perf_counter() - start,
        "terminated_episodes": terminated,
        "summary": summarise(rows),
        "bins": per_bin,
        "episodes": rows,
    }


def save_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


# --------------------------------------------------------------------------- curves


def learning_curves(
    runs: list[Path], task: dict, episodes: int, seed: int, bins: list | None = None
) -> dict:
    """Every checkpoint and the final model of each run, scored on the same episodes."""
    curves = {}
    for run_dir in runs:
        points = []
        final = TrainedPolicy(run_dir)
        for samples in checkpoint_samples(run_dir):
            r = evaluate(TrainedPolicy(run_dir, samples), task, episodes, seed, None, bins)
            points.append({"samples": samples, **r["summary"]})
        r = evaluate(final, task, episodes, seed, None, bins)
        points.append({"samples": final.config["samples"], **r["summary"]})
        curves[str(run_dir)] = {"config": final.config, "points": points}
        print(f"  curve of {run_dir}: {len(points)} points")
    return curves


# --------------------------------------------------------------------------- command line


def mass_edges(text: str) -> list[float]:
    """'1,7,13,20': increasing bin edges (kg), at least two."""
    try:
        edges = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers separated by commas, got {text!r}"
        ) from None
    if len(edges) < 2 or np.any(np.diff(edges) <= 0) or edges[0] <= 0:
        raise argparse.ArgumentTypeError(f"expected >= 2 increasing positive edges, got {text!r}")
    return edges


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument("--policy", nargs="+", default=[], help=POLICY_HELP)
    parser.add_argument(
        "--curve", nargs="+", type=Path, default=[], help="run folders: score every checkpoint"
    )
    parser.add_argument("--plot", type=Path, metavar="PNG", help="learning curves (with --curve)")
    parser.add_argument("--cargo-model", default="estimate", choices=CARGO_MODELS)
    parser.add_argument("--episodes", type=positive_int, default=10, help="per mass bin")
    parser.add_argument(
        "--seed", type=nonnegative_int, default=1000, help="episode k uses seed + k"
    )
    parser.add_argument(
        "--task",
        default=None,
        choices=sorted(LEARNING_TASKS),
        help=f"none: the first run's, else {DEFAULT_TASK}",
    )
    parser.add_argument("--robots", type=int, default=None, help="none: the run's, else 2")
    parser.add_argument("--trajectory", default=None, choices=Trajectory.NAMES)
    parser.add_argument("--max-cycles", type=positive_int, default=None)
    parser.add_argument("--noise", default=None, choices=sorted(NOISE_PROFILES))
    parser.add_argument("--control-hz", type=positive_float, default=None)
    parser.add_argument(
        "--mass-bins",
        type=mass_edges,
        default=None,
        metavar="EDGES",
        help="kg, e.g. 1,7.33,13.67,20: --episodes per bin; none: the task's cargo",
    )
    parser.add_argument(
        "--bound",
        action="store_true",
        help="robot 0's principal-moment bound at the end (records the estimators' updates)",
    )
    parser.add_argument(
        "--correction",
        action="store_true",
        help="the live estimate's change of the scripted thrust from 6 s on, |a_estimate - "
        "a_none| (needs the estimates in the env's observation)",
    )
    parser.add_argument(
        "--mask-block",
        default=None,
        metavar="BLOCK",
        help="diagnostic: trained policies see this observation block (e.g. peer0_wrench) "
        "replaced by their normaliser's mean",
    )
    parser.add_argument(
        "--ablation", action="store_true", help="group run folders into arms over seeds"
    )
    parser.add_argument(
        "--results",
        nargs="+",
        type=Path,
        default=[],
        metavar="FILE",
        help="add the results of earlier --json files scored on the same episodes (task, "
        "--seed, --episodes, --mass-bins: checked) to the table and the ablation",
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the results here")
    parser.add_argument("--video", type=Path, metavar="DIR", help="GIF of episode 0 per policy")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked, with output folders created: every error is the parser's,
    before any model is loaded or episode run."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.policy and not args.curve and not args.results:
        parser.error("give --policy or --curve (or --results)")
    for path in args.results:
        if not path.is_file():
            parser.error(f"--results: {path} is not a file")
    if args.robots is not None and not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
    for spec in args.policy:
        try:
            check_policy_spec(spec)
        except ValueError as err:
            parser.error(f"--policy: {err}")
    for run_dir in args.curve:
        if not (run_dir / "config.json").is_file():
            parser.error(f"--curve: {run_dir} is not a run folder of scripts/train.py")
    if args.plot is not None:
        if not args.curve:
            parser.error("--plot draws the learning curves of --curve: give --curve too")
        output_file(parser, args.plot, "--plot", suffix=".png")
    if args.json is not None:
        output_file(parser, args.json, "--json")
    if args.video is not None:
        output_dir(parser, args.video, "--video")
    return args


TASK_FLAGS = ("robots", "trajectory", "max_cycles", "noise", "control_hz")


def task_of(args: argparse.Namespace, trained: list[dict]) -> dict[str, Any]:
    """The env arguments of the evaluation: the first run's (its decision wrapper's and
    observation's left out: each policy brings its own), else ``--task``'s; the flags override."""
    if trained and args.task is None:
        task = dict(trained[0]["env_kwargs"])
    else:
        task = {**LEARNING_TASKS[args.task or DEFAULT_TASK], "n_robots": 2}
    decision = ("residual_scale", "action_repeat", "base_model", "hide_estimates")
    decision += ("feedforward_obs",)
    for key in (*decision, "observe_estimates", "estimators"):
        task.pop(key, None)
    for flag in TASK_FLAGS:
        value = getattr(args, flag)
        if value is not None:
            task["n_robots" if flag == "robots" else flag] = value
    if isinstance(task.get("cargo_mass_kg"), list):
        task["cargo_mass_kg"] = tuple(task["cargo_mass_kg"])
    return task


def earlier_results(paths: list[Path], task: dict, seed: int, episodes: int, bins: list) -> list:
    """The results of earlier ``--json`` files, each checked to hold the same episodes
    (ValueError otherwise)."""
    same = json.loads(json.dumps([task, seed, episodes, [list(b) for b in bins]]))
    results = []
    for path in paths:
        data = json.loads(path.read_text())
        if [data["task"], data["seed"], data["episodes"], data["mass_bins"]] != same:
            raise ValueError(f"{path} was scored on other episodes (task, seed, episodes, bins)")
        results += data["results"]
    return results


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    policies = [make_policy(spec, args.cargo_model) for spec in args.policy]
    for policy in policies:
        if args.mask_block and isinstance(policy, TrainedPolicy):
            policy.mask(args.mask_block)
    trained = [p.config for p in policies if isinstance(p, TrainedPolicy)]
    trained += [json.loads((run / "config.json").read_text()) for run in args.curve]
    if not trained and args.results:  # the task of the first earlier file's first run
        earlier = [r["config"] for r in json.loads(args.results[0].read_text())["results"]]
        trained = [c for c in earlier if c is not None][:1]
    task = task_of(args, trained)
    bins = mass_bins(args.mass_bins, task)
    previous = earlier_results(args.results, task, args.seed, args.episodes, bins)
    print(f"seed {args.seed} (episodes {args.seed}..{args.seed + args.episodes - 1}); task {task}")
    results = []
    for policy in policies:
        results.append(
            evaluate(
                policy,
                task,
                args.episodes,
                args.seed,
                args.video,
                bins,
                args.bound,
                args.correction,
            )
        )
        print(f"  {policy.name}: {results[-1]['wall_s']:.0f} s")
    results += previous
    if results:
        print_table(results)
    table = ablation(results) if args.ablation else None
    if table is not None:
        print_ablation(table)
    curves = learning_curves(args.curve, task, args.episodes, args.seed, bins) if args.curve else {}
    if curves and args.plot is not None:
        baselines = [
            r for r, p in zip(results, policies, strict=True) if not isinstance(p, TrainedPolicy)
        ]
        plot_curves(curves, baselines, args.plot)
        print(f"wrote {args.plot}")
    if args.json is not None:
        out = {
            "seed": args.seed,
            "episodes": args.episodes,
            "task": task,
            "mass_bins": [list(b) for b in bins],
            "results": results,
        }
        if table is not None:
            out["ablation"] = table
        if curves:
            out["curves"] = curves
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2, default=_json_default) + "\n")
        print(f"wrote {args.json}")
    return 0


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic | np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON-serialisable: {type(x)}")


if __name__ == "__main__":
    sys.exit(main())
