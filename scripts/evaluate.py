"""Score policies on the same seeded episodes of the Astrobee cargo env.

A policy is a run folder of scripts/train.py (``model.zip``, ``vecnormalize.pkl``,
``config.json``), ``scripted`` (``ObservationController`` with ``--cargo-model``) or ``zero``
(all actions zero). Episode k of every policy is reset with seed ``--seed + k``: the same cargo
and the same noise draws. The estimators always run (they do not change the physics), so their
errors are reported whatever the policy observes. Per policy it prints mean and spread (standard
deviation over episodes) of the return (mean over robots), the cargo tracking error (true pose,
mean over the episode and at its end), and the estimators' errors at the end of the episode
(mean over robots); ``--json`` writes every episode and the summaries.

    .venv/bin/python scripts/evaluate.py --policy runs/ppo_est runs/ppo_noest zero scripted \\
        --episodes 10 --json runs/eval.json
    MUJOCO_GL=egl .venv/bin/python scripts/evaluate.py --policy runs/ppo_est --video out/videos

The task (robots, trajectory, episode length, noise) comes from the first run folder's
configuration, else from the flags (default: ``LEARNING_TASK`` of ``astrocargo.envs.wrappers``,
2 robots).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")  # only used with --video

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts/cli.py
from cli import (  # noqa: E402
    Formatter,
    nonnegative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
)

from astrocargo.agents.controllers import ObservationController  # noqa: E402
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs import astrobee_cargo_v0  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402

# Stable-Baselines3 and torch (astrocargo.envs.wrappers imports them) load after the command line
# is parsed: --help and argument errors answer at once.

METRICS = (
    ("return", "return", "{:9.2f}"),
    ("track_pos_m", "pos err m", "{:9.4f}"),
    ("track_att_rad", "att err rad", "{:9.4f}"),
    ("final_pos_m", "end pos m", "{:9.4f}"),
    ("final_att_rad", "end att rad", "{:9.4f}"),
    ("mass_rel_err", "mass err", "{:9.4f}"),
    ("com_err_m", "CoM err m", "{:9.4f}"),
    ("principal_rel_err", "inertia err", "{:9.4f}"),
)


# --------------------------------------------------------------------------- policies


class ZeroPolicy:
    """All actions zero: the cargo drifts only with the noise."""

    name = "zero"
    observe_estimates = True

    def reset(self, env) -> None:
        del env

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.zeros((obs.shape[0], 8))


class ScriptedPolicy:
    """``ObservationController`` (rebuilt each episode: the "truth" model needs the new cargo)."""

    observe_estimates = True

    def __init__(self, cargo_model: str) -> None:
        self.cargo_model = cargo_model
        self.name = f"scripted ({cargo_model})"

    def reset(self, env) -> None:
        self.controller = ObservationController.for_env(env, self.cargo_model)

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.controller.predict(obs)[0]


class TrainedPolicy:
    """A scripts/train.py run: its model, observation normalisation and view, deterministic."""

    def __init__(self, run_dir: Path, samples: int | None = None) -> None:
        """The final model of ``run_dir``, or its checkpoint after ``samples``."""
        from stable_baselines3 import PPO, SAC

        self.config = json.loads((run_dir / "config.json").read_text())
        algo = {"ppo": PPO, "sac": SAC}[self.config["algo"]]
        model_path, stats_path = run_dir / "model.zip", run_dir / "vecnormalize.pkl"
        if samples is not None:
            model_path = run_dir / "checkpoints" / f"rl_model_{samples}_steps.zip"
            stats_path = run_dir / "checkpoints" / f"rl_model_vecnormalize_{samples}_steps.pkl"
        self.model = algo.load(model_path, device="cpu")
        with open(stats_path, "rb") as f:
            self.normalizer = pickle.load(f)
        self.normalizer.training = False
        self.view = self.config["view"]
        self.observe_estimates = self.config["env_kwargs"]["observe_estimates"]
        self.name = str(run_dir) if samples is None else f"{run_dir}@{samples}"

    def reset(self, env) -> None:
        del env

    def act(self, obs: np.ndarray) -> np.ndarray:
        n = obs.shape[0]
        if self.view == "central":
            obs = obs.reshape(1, -1)
        action, _ = self.model.predict(self.normalizer.normalize_obs(obs), deterministic=True)
        return np.asarray(action, dtype=np.float64).reshape(n, -1)


def check_policy_spec(spec: str) -> None:
    """ValueError unless ``spec`` is 'zero', 'scripted' or a run folder of scripts/train.py."""
    if spec in ("zero", "scripted"):
        return
    run_dir = Path(spec)
    if not (run_dir / "model.zip").is_file() or not (run_dir / "config.json").is_file():
        raise ValueError(
            f"policy must be 'zero', 'scripted' or a run folder of scripts/train.py (with "
            f"model.zip and config.json), got {spec!r}"
        )


def make_policy(spec: str, cargo_model: str):
    check_policy_spec(spec)
    if spec == "zero":
        return ZeroPolicy()
    if spec == "scripted":
        return ScriptedPolicy(cargo_model)
    return TrainedPolicy(Path(spec))


# --------------------------------------------------------------------------- episodes


def run_episode(policy, env, seed: int, frames: list | None = None, every: int = 8) -> dict:
    """One seeded episode; returns its metrics."""
    obs_dict, _ = env.reset(seed=seed)
    policy.reset(env)
    agents = env.possible_agents
    total, pos_errs, att_errs, step = 0.0, [], [], 0
    while env.agents:
        obs = np.stack([obs_dict[a] for a in agents])
        actions = policy.act(obs)
        obs_dict, rewards, _, _, infos = env.step(dict(zip(agents, actions, strict=True)))
        total += float(np.mean([rewards[a] for a in agents]))
        pos, att = env.sim.tracking_error()
        pos_errs.append(pos)
        att_errs.append(att)
        if frames is not None and step % every == 0:
            frames.append(env.render())
        step += 1
    last = [infos[a] for a in agents]
    return {
        "seed": seed,
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
    }


def evaluate(policy, task: dict[str, Any], episodes: int, seed: int, video: Path | None) -> dict:
    """Every episode of one policy, and the mean and standard deviation of each metric."""
    env = astrobee_cargo_v0.parallel_env(
        **task,
        observe_estimates=policy.observe_estimates,
        estimators=True,
        render_mode="rgb_array" if video else None,
    )
    start = time.perf_counter()
    rows = []
    for k in range(episodes):
        frames = [] if video and k == 0 else None
        rows.append(run_episode(policy, env, seed + k, frames))
        if frames:
            video.mkdir(parents=True, exist_ok=True)
            safe = "".join(c if c.isalnum() else "_" for c in policy.name).strip("_")
            save_gif(frames, video / f"{safe}.gif", fps=env.metadata["render_fps"] / 8)
    env.close()
    summary = {
        key: {
            "mean": float(np.mean([r[key] for r in rows])),
            "std": float(np.std([r[key] for r in rows])),
        }
        for key, _, _ in METRICS
    }
    terminated = sum(r["termination_reason"] is not None for r in rows)
    return {
        "policy": policy.name,
        "observe_estimates": policy.observe_estimates,
        "wall_s": time.perf_counter() - start,
        "terminated_episodes": terminated,
        "summary": summary,
        "episodes": rows,
    }


def save_gif(frames: list[np.ndarray], path: Path, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


def print_table(results: list[dict]) -> None:
    width = max(len(r["policy"]) for r in results) + 2
    print(f"{'policy':<{width}}" + "".join(f"{label:>20}" for _, label, _ in METRICS))
    for r in results:
        cells = []
        for key, _, fmt in METRICS:
            s = r["summary"][key]
            cells.append(f"{fmt.format(s['mean']).strip()} +- {fmt.format(s['std']).strip()}")
        print(f"{r['policy']:<{width}}" + "".join(f"{c:>20}" for c in cells))
    for r in results:
        if r["terminated_episodes"]:
            print(f"{r['policy']}: {r['terminated_episodes']} episodes ended by termination")


def checkpoint_samples(run_dir: Path) -> list[int]:
    """Sample counts of a run's checkpoints (train.py --checkpoint-every), ascending."""
    names = (run_dir / "checkpoints").glob("rl_model_*_steps.zip")
    return sorted(int(p.stem.split("_")[-2]) for p in names)


def learning_curves(runs: list[Path], task: dict, episodes: int, seed: int) -> dict:
    """Every checkpoint and the final model of each run, scored on the same episodes."""
    curves = {}
    for run_dir in runs:
        points = []
        final = TrainedPolicy(run_dir)
        for samples in checkpoint_samples(run_dir):
            r = evaluate(TrainedPolicy(run_dir, samples), task, episodes, seed, None)
            points.append({"samples": samples, **r["summary"]})
        r = evaluate(final, task, episodes, seed, None)
        points.append({"samples": final.config["samples"], **r["summary"]})
        curves[str(run_dir)] = {"config": final.config, "points": points}
        print(f"  curve of {run_dir}: {len(points)} points")
    return curves


def plot_curves(curves: dict, baselines: list[dict], path: Path) -> None:
    """Return and mean cargo position error against environment steps, with baselines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5), layout="constrained")
    for (key, label), ax in zip(
        (("return", "return (mean over robots)"), ("track_pos_m", "cargo position error [m]")),
        axes,
        strict=True,
    ):
        for curve in curves.values():
            config = curve["config"]
            robots = config["env_kwargs"]["n_robots"]
            steps = [p["samples"] / robots for p in curve["points"]]
            mean = np.array([p[key]["mean"] for p in curve["points"]])
            std = np.array([p[key]["std"] for p in curve["points"]])
            obs = "with" if config["env_kwargs"]["observe_estimates"] else "without"
            minutes = config.get("wall_s", float("nan")) / 60
            # The training's wall time goes in the legend: notes at the curves' ends overlap.
            name = f"PPO {obs} estimates, seed {config.get('seed', '?')} ({minutes:.0f} min)"
            line = ax.plot(steps, mean, marker="o", ms=3, label=name)[0]
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        for base, style in zip(baselines, ("-.", "--", ":"), strict=False):
            ax.axhline(
                base["summary"][key]["mean"], color="k", ls=style, lw=1, label=base["policy"]
            )
        ax.set_xlabel("environment steps (control steps of one copy)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncols=min(3, len(labels)))
    fig.suptitle(
        "Deterministic policy on the same seeded episodes (mean +- std over episodes; "
        "training wall time in brackets)"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument("--policy", nargs="+", default=[], help="run folders, 'zero' or 'scripted'")
    parser.add_argument(
        "--curve", nargs="+", type=Path, default=[], help="run folders: score every checkpoint"
    )
    parser.add_argument("--plot", type=Path, metavar="PNG", help="learning curves (with --curve)")
    parser.add_argument("--cargo-model", default="estimate", choices=("estimate", "none", "truth"))
    parser.add_argument("--episodes", type=positive_int, default=10)
    parser.add_argument(
        "--seed", type=nonnegative_int, default=1000, help="episode k uses seed + k"
    )
    parser.add_argument("--robots", type=int, default=None, help="none: the run's, else 2")
    parser.add_argument("--trajectory", default=None, choices=Trajectory.NAMES)
    parser.add_argument("--max-cycles", type=positive_int, default=None)
    parser.add_argument("--noise", default=None, choices=sorted(NOISE_PROFILES))
    parser.add_argument("--control-hz", type=positive_float, default=None)
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the results here")
    parser.add_argument("--video", type=Path, metavar="DIR", help="GIF of episode 0 per policy")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked, with output folders created: every error is the parser's,
    before any model is loaded or episode run."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.policy and not args.curve:
        parser.error("give --policy or --curve")
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


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from astrocargo.envs.wrappers import LEARNING_TASK

    policies = [make_policy(spec, args.cargo_model) for spec in args.policy]
    trained = [p.config for p in policies if isinstance(p, TrainedPolicy)]
    trained += [json.loads((run / "config.json").read_text()) for run in args.curve]
    base = trained[0]["env_kwargs"] if trained else {**LEARNING_TASK, "n_robots": 2}
    task = {
        "n_robots": args.robots or base["n_robots"],
        "trajectory": args.trajectory or base["trajectory"],
        "max_cycles": args.max_cycles or base["max_cycles"],
        "noise": args.noise or base["noise"],
        "control_hz": args.control_hz or base["control_hz"],
    }
    print(f"seed {args.seed} (episodes {args.seed}..{args.seed + args.episodes - 1}); task {task}")
    results = []
    for policy in policies:
        results.append(evaluate(policy, task, args.episodes, args.seed, args.video))
        print(f"  {policy.name}: {results[-1]['wall_s']:.0f} s")
    if results:
        print_table(results)
    curves = learning_curves(args.curve, task, args.episodes, args.seed) if args.curve else {}
    if curves and args.plot is not None:
        baselines = [
            r for r, p in zip(results, policies, strict=True) if not isinstance(p, TrainedPolicy)
        ]
        plot_curves(curves, baselines, args.plot)
        print(f"wrote {args.plot}")
    if args.json is not None:
        out = {"seed": args.seed, "episodes": args.episodes, "task": task, "results": results}
        if curves:
            out["curves"] = curves
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
