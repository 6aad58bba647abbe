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

from astrocargo.agents.controllers import CARGO_MODELS, ObservationController  # noqa: E402
from astrocargo.agents.excitation import is_trajectory_name, trajectory_choices  # noqa: E402
from astrocargo.agents.feedforward import FeedForwardObservation  # noqa: E402
from astrocargo.agents.model_correction import ModelCorrection  # noqa: E402
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs import astrobee_cargo_v0  # noqa: E402
from astrocargo.envs.config import LEARNING_TASKS, REWARD_TERMS  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402

DEFAULT_TASK = "cargo"
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
    ("mass_conv_s", "mass 5% s", "{:9.1f}"),
    ("saturated", "saturated", "{:9.4f}"),
    ("wall_contact", "wall", "{:9.2f}"),
)
BOUND_METRICS = (
    ("bound_principal_rel", "bound I1/I2/I3"),
    ("filter_principal_rel", "filter I1/I2/I3"),
)
MASS_CONV_TOL = 0.05  # mass_conv_s: the mass error stays within this (relative) from then on
CORRECTION_METRICS = (("correction_mean", "correction"), ("correction_p95", "correction p95"))
POLICY_HELP = (
    "'zero', 'scripted' or a run folder of scripts/train.py (with model.zip and config.json), "
    "or 'feedforward'; 'scripted:MODEL@TRAJECTORY' picks the cargo model (estimate, none, "
    "truth) and trajectory; 'feedforward': the no-model controller plus u_ff of the live "
    "estimate, held ('feedforward:prior': of the estimator's prior); 'teacher': the no-model "
    "controller plus the live-estimate correction, held (the imitation's oracle); "
    "'RUN@SAMPLES': the run's checkpoint after SAMPLES samples"
)


# --------------------------------------------------------------------------- policies


class ZeroPolicy:
    """All actions zero: the cargo drifts only with the noise."""

    name = "zero"
    observe_estimates = True
    trajectory = None
    decision = {}

    def reset(self, env) -> None:
        del env

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.zeros((obs.shape[0], 8))


class ScriptedPolicy:
    """``ObservationController`` (rebuilt each episode: the "truth" model needs the new cargo),
    on the task's trajectory or on ``trajectory``."""

    observe_estimates = True
    decision = {}

    def __init__(self, cargo_model: str, trajectory: str | None = None) -> None:
        self.cargo_model = cargo_model
        self.trajectory = trajectory
        where = f" on {trajectory}" if trajectory else ""
        self.name = f"scripted ({cargo_model}){where}"

    def reset(self, env) -> None:
        self.controller = ObservationController.for_env(env, self.cargo_model)

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.controller.predict(obs)[0]


class FeedForwardPolicy:
    """The residual a policy with the feed-forward input could learn first: its input as it
    is, a = u_ff (of the live estimate, or with ``source`` "prior" of the estimator's prior),
    decided every ``action_repeat`` steps (the cargo task's) and held, added to the no-model
    scripted controller's thrust at every step (residual scale 1)."""

    observe_estimates = True
    trajectory = None
    decision = {}

    def __init__(self, action_repeat: int, source: str = "estimate") -> None:
        self.action_repeat, self.source = action_repeat, source
        self.name = f"feedforward ({source}; no model + u_ff held)"

    def reset(self, env) -> None:
        self.base = ObservationController.for_env(env, "none")
        self.feedforward = FeedForwardObservation(env, self.source)
        self.agents, self.steps = list(env.possible_agents), 0

    def decide(self, obs: np.ndarray) -> np.ndarray:
        u_ff = self.feedforward(dict(zip(self.agents, obs, strict=True)))
        return np.stack([u_ff[a] for a in self.agents])

    def act(self, obs: np.ndarray) -> np.ndarray:
        from astrocargo.envs.decision import residual_actions

        if self.steps % self.action_repeat == 0:
            self.held = self.decide(obs)
        self.steps += 1
        return residual_actions(self.base.predict(obs)[0], self.held, 1.0)


class TeacherHeldPolicy(FeedForwardPolicy):
    """The imitation's oracle: the teacher's label as a policy could hold it, i.e. the residual
    that makes the no-model controller the live-estimate one (``teacher_residual``), computed
    at each decision's first step, clipped to [-1, 1] and held over the decision (residual scale
    1, the cargo task's ``action_repeat``)."""

    def __init__(self, action_repeat: int) -> None:
        super().__init__(action_repeat)
        self.name = "teacher held (no model + the live-estimate correction, held)"

    def reset(self, env) -> None:
        super().reset(env)
        self.teacher = ObservationController.for_env(env, "estimate")

    def decide(self, obs: np.ndarray) -> np.ndarray:
        from astrocargo.envs.decision import teacher_residual

        label = teacher_residual(self.teacher.predict(obs)[0], self.base.predict(obs)[0], 1.0)
        return np.clip(label, -1.0, 1.0)


class TrainedPolicy:
    """A scripts/train.py run: its model, observation normalisation and view, deterministic,
    acting at the env's control rate as its ``DecisionEnv`` did in training: a new decision every
    ``action_repeat`` steps from the observation less the estimates if it hid them, held in
    between, added (times ``residual_scale``) to the action of its scripted base controller
    (``base_model``) at every step if residual; with ``feedforward_obs`` the decision's
    observation ends with the cargo model's feed-forward, as in ``DecisionEnv``."""

    trajectory = None

    def __init__(self, run_dir: Path, samples: int | None = None) -> None:
        """The final model of ``run_dir``, or its checkpoint after ``samples``."""
        from stable_baselines3 import PPO, SAC, TD3

        self.config = json.loads((run_dir / "config.json").read_text())
        if samples is not None:
            self.config["checkpoint_samples"] = samples
        algo = {"ppo": PPO, "sac": SAC, "td3": TD3}[self.config["algo"]]
        model_path, stats_path = run_dir / "model.zip", run_dir / "vecnormalize.pkl"
        if samples is not None:
            model_path = run_dir / "checkpoints" / f"rl_model_{samples}_steps.zip"
            stats_path = run_dir / "checkpoints" / f"rl_model_vecnormalize_{samples}_steps.pkl"
        from astrocargo.envs.wrappers import fast_inference

        self.model = fast_inference(algo.load(model_path, device="cpu"))
        with open(stats_path, "rb") as f:
            self.normalizer = pickle.load(f)
        self.normalizer.training = False
        self.view = self.config["view"]
        kwargs = self.config["env_kwargs"]
        self.observe_estimates = kwargs["observe_estimates"]  # the env's observation
        self.hide_estimates = bool(kwargs.get("hide_estimates", False))
        self.base_model = kwargs.get("base_model", "none")
        self.residual_scale = float(kwargs.get("residual_scale", 0.0))
        self.action_repeat = int(kwargs.get("action_repeat", 1))
        self.feedforward_obs = kwargs.get("feedforward_obs")
        self.feedforward = None
        self.agents: list[str] = []
        self.decision = {"residual_scale": self.residual_scale, "action_repeat": self.action_repeat}
        self.name = str(run_dir) if samples is None else f"{run_dir}@{samples}"
        self.base = None
        self.held: np.ndarray | None = None
        self.steps = 0
        self.policy_obs = slice(None)
        self.masked: str | None = None
        self.mask_cols = np.zeros(0, dtype=np.int64)

    def mask(self, block: str) -> None:
        """A diagnostic: the observation block ``block`` (``sim.obs_layout``'s name) replaced by
        the normaliser's mean, i.e. the policy's normalised input there set to zero."""
        self.masked = block
        self.config["masked_block"] = block
        self.name += f" (masked {block})"

    def reset(self, env) -> None:
        from astrocargo.envs.decision import policy_observation_index

        if self.masked is not None:
            layout = env.sim.obs_layout
            if self.masked not in layout or self.masked == "all":
                raise ValueError(f"no observation block {self.masked!r}; blocks: {list(layout)}")
            seen = policy_observation_index(layout, self.hide_estimates)
            block = np.arange(layout[self.masked].start, layout[self.masked].stop)
            self.mask_cols = np.flatnonzero(np.isin(seen, block))
        self.steps, self.held = 0, None
        # The observation as it is unless hidden: a copy would change torch's float rounding.
        if self.hide_estimates:
            self.policy_obs = policy_observation_index(env.sim.obs_layout, True)
        if self.residual_scale:
            self.base = ObservationController.for_env(env, self.base_model)
        if self.feedforward_obs:
            self.feedforward = FeedForwardObservation(env, self.feedforward_obs)
        self.agents = list(env.possible_agents)

    def decide(self, obs: np.ndarray) -> np.ndarray:
        """The model's deterministic action (n, 8) from the policy's part of the env's
        observations (n, obs_dim): after ``reset``, the part it saw in training."""
        n = obs.shape[0]
        rows = [row[self.policy_obs] for row in obs]  # rows as DecisionEnv gives them
        if self.feedforward is not None:
            u_ff = self.feedforward(dict(zip(self.agents, obs, strict=True)))
            rows = [np.concatenate([r, u_ff[a]]) for a, r in zip(self.agents, rows, strict=True)]
        obs = np.stack(rows)
        obs[:, self.mask_cols] = self.normalizer.obs_rms.mean[self.mask_cols]
        if self.view == "central":
            obs = obs.reshape(1, -1)
        action, _ = self.model.predict(self.normalizer.normalize_obs(obs), deterministic=True)
        return np.asarray(action, dtype=np.float64).reshape(n, -1)

    def act(self, obs: np.ndarray) -> np.ndarray:
        from astrocargo.envs.decision import residual_actions

        if self.steps % self.action_repeat == 0:
            self.held = self.decide(obs)
        self.steps += 1
        if not self.residual_scale:
            return self.held
        return residual_actions(self.base.predict(obs)[0], self.held, self.residual_scale)


def parse_scripted(spec: str) -> tuple[str, str | None] | None:
    """(cargo model or '', trajectory or None) of 'scripted[:MODEL][@TRAJECTORY]', else None."""
    head, _, trajectory = spec.partition("@")
    name, _, model = head.partition(":")
    if name != "scripted":
        return None
    return model, trajectory or None


def check_policy_spec(spec: str) -> None:
    """ValueError unless ``spec`` is 'zero', a scripted spec or a run folder of scripts/train.py."""
    if spec in ("zero", "feedforward", "feedforward:prior", "teacher"):
        return
    scripted = parse_scripted(spec)
    if scripted is not None:
        model, trajectory = scripted
        if model and model not in CARGO_MODELS:
            raise ValueError(f"cargo model must be one of {CARGO_MODELS}, got {model!r}")
        if trajectory is not None and not is_trajectory_name(trajectory):
            raise ValueError(f"unknown trajectory {trajectory!r}; {trajectory_choices()}")
        return
    run_dir, samples = run_and_checkpoint(spec)
    if not (run_dir / "model.zip").is_file() or not (run_dir / "config.json").is_file():
        raise ValueError(f"policy must be {POLICY_HELP}, got {spec!r}")
    if samples is not None and samples not in checkpoint_samples(run_dir):
        raise ValueError(f"{run_dir} has no checkpoint after {samples} samples")


def run_and_checkpoint(spec: str) -> tuple[Path, int | None]:
    """'RUN@SAMPLES' -> (RUN, SAMPLES): the run's checkpoint after SAMPLES; 'RUN' -> (RUN,
    None): its final model."""
    head, sep, tail = spec.rpartition("@")
    if sep and tail.isdigit():
        return Path(head), int(tail)
    return Path(spec), None


def make_policy(spec: str, cargo_model: str):
    check_policy_spec(spec)
    if spec == "zero":
        return ZeroPolicy()
    if spec == "teacher":
        return TeacherHeldPolicy(LEARNING_TASKS[DEFAULT_TASK]["action_repeat"])
    if spec.startswith("feedforward"):
        source = "prior" if spec.endswith(":prior") else "estimate"
        return FeedForwardPolicy(LEARNING_TASKS[DEFAULT_TASK]["action_repeat"], source)
    scripted = parse_scripted(spec)
    if scripted is not None:
        return ScriptedPolicy(scripted[0] or cargo_model, scripted[1])
    return TrainedPolicy(*run_and_checkpoint(spec))


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


def _cell(stat: dict, fmt: str) -> str:
    mean, std = np.atleast_1d(stat["mean"]), np.atleast_1d(stat["std"])
    if len(mean) > 1:
        return "/".join(fmt.format(m).strip() for m in mean)
    return f"{fmt.format(mean[0]).strip()} +- {fmt.format(std[0]).strip()}"


def print_table(results: list[dict]) -> None:
    width = max(len(r["policy"]) for r in results) + 14
    bound = [(k, label) for k, label in BOUND_METRICS if k in results[0]["summary"]]
    bound += [(k, label) for k, label in CORRECTION_METRICS if k in results[0]["summary"]]
    print(
        f"{'policy':<{width}}"
        + "".join(f"{label:>20}" for _, label, _ in METRICS)
        + "".join(f"{label:>22}" for _, label in bound)
    )
    for r in results:
        for name, summary in [("all", r["summary"])] + (
            list(r["bins"].items()) if len(r["bins"]) > 1 else []
        ):
            cells = [_cell(summary[key], fmt) for key, _, fmt in METRICS]
            cells += [_cell(summary[key], "{:.3f}") if key in summary else "-" for key, _ in bound]
            print(
                f"{r['policy'] + ' [' + name + ']':<{width}}"
                + "".join(f"{c:>20}" for c in cells[: len(METRICS)])
                + "".join(f"{c:>22}" for c in cells[len(METRICS) :])
            )
    for r in results:
        if r["terminated_episodes"]:
            print(f"{r['policy']}: {r['terminated_episodes']} episodes ended by termination")


# --------------------------------------------------------------------------- ablation


ABLATION_METRICS = ("track_pos_m", "track_att_rad", "return")


def arm_key(config: dict) -> str:
    """A run's arm: its configuration without the seed (algorithm, residual scale and base,
    feed-forward input, training length or checkpoint, view, task, estimates observed)."""
    kwargs = config["env_kwargs"]
    residual = kwargs.get("residual_scale", 0.0)
    base = kwargs.get("base_model", "none")
    on = f" on {base}" if base != "none" else ""
    kind = f"{config['algo'].upper()}{f' residual x{residual:g}{on}' if residual else ''}"
    if kwargs.get("feedforward_obs"):
        kind += " + feed-forward input"
    if "imitation" in config:
        kind += ", imitation of the live-estimate controller"
    elif "init_from" in config:
        kind += ", from imitation"
    if "masked_block" in config:
        kind += f", {config['masked_block']} masked"
    if "checkpoint_samples" in config:  # a checkpoint is an arm of its own training length
        kind += f" (checkpoint at {config['checkpoint_samples']} samples)"
    elif config.get("timesteps"):
        kind += f" ({config['timesteps']} samples)"
    obs = "with" if policy_observes_estimates(kwargs) else "without"
    return f"{kind}, {config['view']}, task {config.get('task', '?')}, {obs} estimates"


def policy_observes_estimates(env_kwargs: dict) -> bool:
    """Whether a run's policy saw the estimates (the env observed them and did not hide them)."""
    return bool(env_kwargs["observe_estimates"]) and not env_kwargs.get("hide_estimates", False)


def ablation(results: list[dict]) -> dict:
    """Per arm and mass bin: each seed's mean over the episodes, their mean and standard
    deviation (ddof 1) over seeds; per pair of arms differing only in observing the estimates:
    the difference of the means (with - without) and whether it exceeds the larger of the two
    arms' seed spreads."""
    arms: dict[str, dict] = {}
    for r in results:
        if r["config"] is None:
            continue
        arm = arms.setdefault(
            arm_key(r["config"]), {"seeds": [], "bins": {}, "config": r["config"]}
        )
        arm["seeds"].append(r["config"]["seed"])
        for name, summary in r["bins"].items():
            per = arm["bins"].setdefault(name, {m: [] for m in ABLATION_METRICS})
            for m in ABLATION_METRICS:
                per[m].append(float(np.atleast_1d(summary[m]["mean"])[0]))
    for arm in arms.values():
        for per in arm["bins"].values():
            for m in ABLATION_METRICS:
                values = np.array(per[m])
                spread = float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")
                per[m] = {"per_seed": values.tolist(), "mean": float(values.mean()), "std": spread}
    pairs = []
    for key, arm in arms.items():
        if not policy_observes_estimates(arm["config"]["env_kwargs"]):
            continue
        other = key.replace("with estimates", "without estimates")
        if other not in arms:
            continue
        diffs = {}
        for name, per in arm["bins"].items():
            if name not in arms[other]["bins"]:
                continue
            base = arms[other]["bins"][name]
            diffs[name] = {}
            for m in ABLATION_METRICS:
                diff = per[m]["mean"] - base[m]["mean"]
                spread = max(per[m]["std"], base[m]["std"])
                diffs[name][m] = {
                    "with_minus_without": diff,
                    "seed_spread": spread,
                    "exceeds_spread": bool(abs(diff) > spread) if np.isfinite(spread) else None,
                }
        pairs.append({"with": key, "without": other, "bins": diffs})
    for arm in arms.values():
        del arm["config"]
    return {"arms": arms, "pairs": pairs}


def print_ablation(table: dict) -> None:
    print("\nablation: per mass bin, mean over seeds (seed std; per seed), pos. error mm")
    for key, arm in table["arms"].items():
        print(f"  {key}: seeds {arm['seeds']}")
        for name, per in arm["bins"].items():
            s = per["track_pos_m"]
            seeds = ", ".join(f"{1e3 * v:.1f}" for v in s["per_seed"])
            print(f"    {name:>12}: {1e3 * s['mean']:.1f} ({1e3 * s['std']:.1f}; {seeds})")
    for pair in table["pairs"]:
        print(f"  {pair['with']} minus {pair['without']}:")
        for name, d in pair["bins"].items():
            x = d["track_pos_m"]
            verdict = {True: "exceeds", False: "within", None: "one seed:"}[x["exceeds_spread"]]
            print(
                f"    {name:>12}: {1e3 * x['with_minus_without']:+.1f} mm, {verdict} the seed "
                f"spread {1e3 * x['seed_spread']:.1f} mm"
            )


# --------------------------------------------------------------------------- curves


def checkpoint_samples(run_dir: Path) -> list[int]:
    """Sample counts of a run's checkpoints (train.py --checkpoint-every), ascending."""
    names = (run_dir / "checkpoints").glob("rl_model_*_steps.zip")
    return sorted(int(p.stem.split("_")[-2]) for p in names)


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


def plot_curves(curves: dict, baselines: list[dict], path: Path) -> None:
    """Return and mean cargo position error against decisions, with baselines."""
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
            mean = np.array([p[key]["mean"] for p in curve["points"]], dtype=float)
            std = np.array([p[key]["std"] for p in curve["points"]], dtype=float)
            minutes = config.get("wall_s", float("nan")) / 60
            # The training's wall time goes in the legend: notes at the curves' ends overlap.
            name = f"{arm_key(config)}, seed {config.get('seed', '?')} ({minutes:.0f} min)"
            line = ax.plot(steps, mean, marker="o", ms=3, label=name)[0]
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        for base, style in zip(baselines, ("-.", "--", ":"), strict=False):
            ax.axhline(
                base["summary"][key]["mean"], color="k", ls=style, lw=1, label=base["policy"]
            )
        ax.set_xlabel("decisions (samples / robots, all copies together)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncols=min(2, len(labels)))
    fig.suptitle(
        "Deterministic policy on the same seeded episodes (mean +- std over episodes; "
        "training wall time in brackets)"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
