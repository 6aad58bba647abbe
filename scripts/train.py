"""Train PPO or SAC on the Astrobee cargo env with Stable-Baselines3, or PPO with RLlib on Ray.

Two views of the multi-robot env:
- ``shared`` (default): one policy shared by all robots, each acting on its own observation
  (``SharedPolicyVecEnv``: every robot of every copy is one slot);
- ``central``: one policy sees all observations and sends all actions (``CentralizedCargoEnv``).

The task is one of ``LEARNING_TASKS`` (``--task``, default ``cargo``: 1-20 kg cargo, 30 s, env
at 62.5 Hz, decisions at 12.5 Hz); ``--residual-scale S`` > 0 trains a residual policy whose
action, times S, is added to the thrust of the scripted controller (``DecisionEnv``), which has no
cargo model (``--base-model none``) or each robot's live estimate (``--base-model estimate``);
``--feedforward-obs`` adds to the policy's observation the thrust the cargo model adds to that
controller's feed-forward (from the live estimate; with ``--no-estimates`` from the prior).
PPO, SAC or TD3 (``--algo``). Observations and rewards are normalised with ``VecNormalize``.
The run folder receives ``model.zip``, ``vecnormalize.pkl``, ``config.json`` (every setting, the
task, the seed, the wall time), ``monitor.csv`` (one row per finished episode of one robot or of
the central agent), ``checkpoints/`` and TensorBoard logs under ``tb/``. ``--timesteps`` counts
samples as SB3 does: one per robot per decision in the shared view (decisions = timesteps /
robots; a decision is ``action_repeat`` control steps), one per decision in the central view.

    .venv/bin/python scripts/train.py --task cargo --algo ppo --residual-scale 0.3 \\
        --timesteps 300000 --copies 2 --seed 1 --checkpoint-every 50000 --log-dir runs/res_est_1
    .venv/bin/python scripts/train.py ... --no-estimates --log-dir runs/res_noest_1
    .venv/bin/tensorboard --logdir runs

``--backend rllib`` (needs the ray extra, ``bash scripts/setup.sh --dev``) trains PPO with RLlib
instead, for runs that outgrow one machine: the parallel env is wrapped in RLlib's
``ParallelPettingZooEnv``, all robots act with one shared policy (the ``shared`` view), and
``--env-runners`` sampling actors are spread over the Ray cluster at ``--ray-address`` (default
``$RAY_ADDRESS``, else a new local instance; ``--copies`` and ``--subprocess`` are SB3's); the
learner runs in this process. Observations are normalised with RLlib's ``MeanStdFilter`` (rewards
are not). ``--timesteps`` counts robot samples as above. The run folder receives ``checkpoint/``
(``Algorithm.from_checkpoint`` restores it), ``config.json`` and ``progress.csv`` (one row per
training iteration).

    .venv/bin/python scripts/train.py --backend rllib --ray-address HEAD:6379 --env-runners 8 \\
        --timesteps 600000 --seed 1 --log-dir runs/rllib_ppo
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import csv
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only add hand-offs

import numpy as np  # noqa: E402
import stable_baselines3  # noqa: E402
import torch  # noqa: E402
from stable_baselines3 import PPO, SAC, TD3  # noqa: E402
from stable_baselines3.common.base_class import BaseAlgorithm  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback  # noqa: E402
from stable_baselines3.common.noise import NormalActionNoise  # noqa: E402
from stable_baselines3.common.vec_env import (  # noqa: E402
    DummyVecEnv,
    SubprocVecEnv,
    VecEnv,
    VecMonitor,
    VecNormalize,
)

from astrocargo.agents.imitation import initialise_from  # noqa: E402
from astrocargo.agents.trajectories import Trajectory  # noqa: E402
from astrocargo.envs.config import LEARNING_TASKS  # noqa: E402
from astrocargo.envs.decision import BASE_MODELS, check_decision_args  # noqa: E402
from astrocargo.envs.sensors import NOISE_PROFILES  # noqa: E402
from astrocargo.envs.world import MAX_ROBOTS  # noqa: E402
from astrocargo.envs.wrappers import (  # noqa: E402
    CentralizedCargoEnv,
    fast_inference,
    fast_normalization,
    make_vec_env,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling cli.py, ray_backend.py
from cli import (  # noqa: E402
    Formatter,
    nonnegative_float,
    nonnegative_int,
    output_dir,
    positive_float,
    positive_int,
)
from ray_backend import import_ray, ray_connection  # noqa: E402

ALGOS = {"ppo": PPO, "sac": SAC, "td3": TD3}
DEFAULT_TASK = "cargo"
RLLIB_TASK = "figure8_10s"  # RLlib trains on the bare env: a task without DecisionEnv
VIEWS = ("shared", "central")
BACKENDS = ("sb3", "rllib")
RLLIB_ENV = "astrocargo_v0"  # RLlib's registry name of the wrapped parallel env
RLLIB_POLICY = "shared"  # the one policy every robot acts with
# Hyperparameters, all in one place. PPO's n_steps is per slot: a rollout holds
# n_steps * slots samples (slots = copies * robots in the shared view).
HYPERPARAMS: dict[str, dict[str, Any]] = {
    "ppo": {
        # Large rollouts (n_steps * 4 slots = 4096 samples) and few epochs: one action's effect
        # on the cargo is small against the noise, so gradients need many samples.
        "n_steps": 1024,
        "batch_size": 512,
        "n_epochs": 5,
        "learning_rate": 3e-4,
        "gamma": 0.99,  # 8 s at 12.5 Hz: the cargo answers a push over seconds
        "gae_lambda": 0.98,
        "clip_range": 0.2,
        "ent_coef": 0.0,
        # Small initial exploration: torque noise alone doubles the attitude error.
        "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -1.5},
    },
    # RLlib's PPO (--backend rllib), the SB3 values where RLlib has them. Its batch counts
    # environment steps: 2048 steps of 2 robots are SB3's rollout of 4096 samples. Keys of
    # RLlib's DefaultModelConfig (fcnet_hiddens, vf_share_layers) go to the model.
    "rllib_ppo": {
        "train_batch_size_per_learner": 2048,
        "minibatch_size": 512,
        "num_epochs": 5,
        "lr": 3e-4,
        "gamma": 0.99,
        "lambda_": 0.98,
        "clip_param": 0.2,
        "entropy_coeff": 0.0,
        "fcnet_hiddens": [64, 64],
        "vf_share_layers": False,
    },
    "sac": {
        "learning_rate": 3e-4,
        "buffer_size": 300_000,
        "batch_size": 256,
        "learning_starts": 5_000,
        "gamma": 0.99,
        "tau": 0.005,
        "train_freq": 1,
        "gradient_steps": 1,
        "policy_kwargs": {"net_arch": [64, 64]},
    },
    "td3": {
        "learning_rate": 1e-3,
        "buffer_size": 300_000,
        "batch_size": 256,
        "learning_starts": 5_000,
        "gamma": 0.99,
        "tau": 0.005,
        "train_freq": 1,
        "gradient_steps": 1,
        # Gaussian exploration noise on the action (std, in action units): NormalActionNoise.
        "action_noise_std": 0.1,
        "policy_kwargs": {"net_arch": [64, 64]},
    },
}


class TrackingCostCallback(BaseCallback):
    """Logs each finished episode's mean tracking cost (m; the reward's track term over w_track,
    sign flipped) as ``episode/track_cost_m`` to TensorBoard."""

    def __init__(self, w_track: float = 1.0) -> None:
        super().__init__()
        self.w_track = w_track
        self.sums: np.ndarray | None = None
        self.counts: np.ndarray | None = None

    def _on_step(self) -> bool:
        infos, dones = self.locals["infos"], self.locals["dones"]
        if self.sums is None:
            self.sums, self.counts = np.zeros(len(infos)), np.zeros(len(infos))
        finished = []
        for k, info in enumerate(infos):
            terms = info.get("agents", {None: info})  # central view: per-robot infos inside
            self.sums[k] += np.mean([i["reward_track"] for i in terms.values()])
            self.counts[k] += 1
            if dones[k]:
                finished.append(-self.sums[k] / self.counts[k] / self.w_track)
                self.sums[k] = self.counts[k] = 0.0
        if finished:
            self.logger.record_mean("episode/track_cost_m", float(np.mean(finished)))
        return True


def env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of ``cargo_env_fn`` for this run: the task's, then the flags' and
    ``--env`` overrides, ``residual_scale`` and the estimators."""
    kwargs = {**LEARNING_TASKS[task_name(args)], "n_robots": args.robots}
    for flag in ("trajectory", "noise", "max_cycles", "control_hz", "action_repeat"):
        if getattr(args, flag) is not None:
            kwargs[flag] = getattr(args, flag)
    kwargs.update(dict(args.env or []))
    kwargs["residual_scale"] = args.residual_scale
    kwargs["base_model"] = args.base_model
    # The estimators do not change the physics: without their outputs in the observation they
    # are only cost, so they are switched off (evaluate.py runs them, to score them); a reward
    # with an information term needs them, and so does the "estimate" base controller, which
    # reads them from the env's observation: --no-estimates then hides them from the policy.
    # Without the estimators the peers' messages (peer slots) stay zero, while evaluate.py runs
    # them: --hidden-estimators keeps them running, hidden, so the policy trains on the peer
    # slots it is evaluated with.
    observed = args.estimates or args.base_model == "estimate" or args.hidden_estimators
    kwargs["observe_estimates"] = observed
    kwargs["hide_estimates"] = observed and not args.estimates
    kwargs["estimators"] = observed or bool(kwargs.get("w_info", 0.0))
    # The cargo model's feed-forward as an input: from the live estimate where the policy
    # observes the estimates, else from the estimator's prior (the same form, no cargo).
    kwargs["feedforward_obs"] = None
    if args.feedforward_obs:
        kwargs["feedforward_obs"] = "estimate" if args.estimates else "prior"
    return kwargs


def task_name(args: argparse.Namespace) -> str:
    """``--task``, else the backend's default: SB3 ``DEFAULT_TASK``, RLlib ``RLLIB_TASK``."""
    if args.task is not None:
        return args.task
    return RLLIB_TASK if args.backend == "rllib" else DEFAULT_TASK


def bare_env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``env_kwargs`` without the decision wrapper's (RLlib's env is the bare parallel env)."""
    kwargs = env_kwargs(args)
    for key in ("residual_scale", "action_repeat", "base_model", "hide_estimates"):
        del kwargs[key]
    del kwargs["feedforward_obs"]
    return kwargs


def make_training_env(args: argparse.Namespace, seed: int, log_dir: Path | None = None) -> VecEnv:
    """The view's VecEnv (copies seeded seed, seed + 1, ...), with episode monitoring
    (``log_dir/monitor.csv`` if given)."""
    kwargs = env_kwargs(args)
    subprocess = args.subprocess and args.copies > 1
    if args.view == "shared":
        venv: VecEnv = make_vec_env(args.copies, seed=seed, subprocess=subprocess, **kwargs)
    else:
        fns = [lambda: CentralizedCargoEnv(**kwargs) for _ in range(args.copies)]
        venv = SubprocVecEnv(fns) if subprocess else DummyVecEnv(fns)
        venv.seed(seed)
    return VecMonitor(venv, filename=None if log_dir is None else str(log_dir / "monitor.csv"))


def build_model(
    args: argparse.Namespace, seed: int, log_dir: Path | None = None
) -> tuple[BaseAlgorithm, dict[str, Any]]:
    """The algorithm on its normalised, monitored VecEnv (TensorBoard logs under
    ``log_dir/tb`` if given), and its hyperparameters."""
    torch.set_num_threads(args.torch_threads)
    hyper = {**HYPERPARAMS[args.algo], **dict(args.hyperparams or [])}
    venv = make_training_env(args, seed, log_dir)
    # Compiled running statistics: the same numbers as SB3's (envs/wrappers.py).
    venv = fast_normalization(
        VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=hyper["gamma"])
    )
    kwargs = dict(hyper)
    noise_std = kwargs.pop("action_noise_std", None)
    if noise_std is not None:
        n_actions = venv.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(
            np.zeros(n_actions), np.full(n_actions, noise_std)
        )
    model = ALGOS[args.algo](
        "MlpPolicy",
        venv,
        seed=seed,
        verbose=args.verbose,
        tensorboard_log=None if log_dir is None else str(log_dir / "tb"),
        device="cpu",
        **kwargs,
    )
    return fast_inference(model), hyper


def train(args: argparse.Namespace) -> tuple[BaseAlgorithm, Path]:
    """Train, save model, normalisation statistics and configuration; returns the model and
    the run folder."""
    seed = args.seed if args.seed is not None else int(np.random.default_rng().integers(2**31))
    print(f"seed {seed}")
    log_dir = Path(args.log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    model, hyper = build_model(args, seed, log_dir)
    if args.init_from is not None:  # imitation first (scripts/imitate.py), then PPO
        initialise_from(model, args.init_from)
        fast_normalization(model.get_env())  # copied statistics may be SB3's class (older runs)
    config = {
        "algo": args.algo,
        "view": args.view,
        "task": task_name(args),
        "seed": seed,
        "timesteps": args.timesteps,
        "copies": args.copies,
        "subprocess": args.subprocess,
        "env_kwargs": env_kwargs(args),
        "hyperparams": hyper,
        "versions": {
            "python": platform.python_version(),
            "stable_baselines3": stable_baselines3.__version__,
            "torch": torch.__version__,
        },
        "command": " ".join(sys.argv),
    }
    if args.init_from is not None:
        init = json.loads((args.init_from / "config.json").read_text())
        config["init_from"] = {"run": str(args.init_from), "wall_s": init.get("wall_s")}
    (log_dir / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    start = time.perf_counter()
    callbacks: list[BaseCallback] = [TrackingCostCallback()]
    if args.checkpoint_every:
        # Saved every checkpoint_every samples: for learning curves of the deterministic policy.
        calls = max(1, args.checkpoint_every // model.get_env().num_envs)
        callbacks.append(
            CheckpointCallback(calls, str(log_dir / "checkpoints"), save_vecnormalize=True)
        )
    model.learn(
        total_timesteps=args.timesteps,
        callback=callbacks,
        progress_bar=args.progress_bar,
        tb_log_name=args.algo,
    )
    config["wall_s"] = time.perf_counter() - start
    config["samples"] = int(model.num_timesteps)
    model.save(log_dir / "model.zip")
    venv = model.get_env()
    venv.save(str(log_dir / "vecnormalize.pkl"))
    (log_dir / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    venv.close()
    print(
        f"trained {model.num_timesteps} samples in {config['wall_s']:.0f} s (seed {seed}); "
        f"saved to {log_dir}"
    )
    return model, log_dir


# ------------------------------------------------------------------------------- RLlib
def make_rllib_env(env_config: dict[str, Any]):
    """RLlib's env creator: ``astrobee_cargo_v0.parallel_env(**env_config)`` wrapped in
    ``ParallelPettingZooEnv`` (runs in the env runners)."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from astrocargo.envs import astrobee_cargo_v0

    return ParallelPettingZooEnv(astrobee_cargo_v0.parallel_env(**env_config))


def _shared_policy(agent_id: str, episode: Any, **kwargs: Any) -> str:
    return RLLIB_POLICY


def _observation_filter(env: Any, spaces: Any, device: Any):
    from ray.rllib.connectors.env_to_module.mean_std_filter import MeanStdFilter

    return MeanStdFilter(multi_agent=True)


def build_rllib_config(args: argparse.Namespace, seed: int, hyper: dict[str, Any]):
    """RLlib ``PPOConfig``: the wrapped env, one shared policy, ``--env-runners`` env runners."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    model_keys = {f.name for f in dataclasses.fields(DefaultModelConfig)}
    model = {k: v for k, v in hyper.items() if k in model_keys}
    training = {k: v for k, v in hyper.items() if k not in model_keys}
    return (
        PPOConfig()
        .environment(RLLIB_ENV, env_config=bare_env_kwargs(args))
        .framework("torch")
        .env_runners(
            num_env_runners=args.env_runners,
            num_envs_per_env_runner=1,
            num_cpus_per_env_runner=1,
            env_to_module_connector=_observation_filter,
        )
        .multi_agent(policies={RLLIB_POLICY}, policy_mapping_fn=_shared_policy)
        .rl_module(model_config=DefaultModelConfig(**model))
        .training(**training)
        .debugging(seed=seed)
    )


def train_rllib(args: argparse.Namespace) -> Path:
    """Train PPO with RLlib until ``--timesteps`` robot samples; save a checkpoint, the
    configuration and per-iteration progress. Returns the run folder."""
    ray = import_ray("--backend rllib needs Ray and RLlib")
    from ray.tune.registry import register_env

    seed = args.seed if args.seed is not None else int(np.random.default_rng().integers(2**31))
    print(f"seed {seed}")
    torch.set_num_threads(args.torch_threads)
    log_dir = Path(args.log_dir).resolve()
    log_dir.mkdir(parents=True, exist_ok=True)
    hyper = {**HYPERPARAMS["rllib_ppo"], **dict(args.hyperparams or [])}
    config = {
        "backend": "rllib",
        "algo": "ppo",
        "view": "shared",
        "seed": seed,
        "timesteps": args.timesteps,
        "env_runners": args.env_runners,
        "ray_address": args.ray_address,
        "env_kwargs": bare_env_kwargs(args),
        "hyperparams": hyper,
        "versions": {
            "python": platform.python_version(),
            "ray": ray.__version__,
            "torch": torch.__version__,
        },
        "command": " ".join(sys.argv),
    }
    (log_dir / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    with ray_connection(ray, args.ray_address):
        module = sys.modules[make_rllib_env.__module__]
        if module.__name__ != "__main__":
            # Imported (tests): ship this script's functions to the env runners by value.
            ray.cloudpickle.register_pickle_by_value(module)
        register_env(RLLIB_ENV, make_rllib_env)
        algo = build_rllib_config(args, seed, hyper).build_algo()
        start = time.perf_counter()
        samples, iteration, next_checkpoint = 0, 0, args.checkpoint_every
        with open(log_dir / "progress.csv", "w", newline="") as f:
            progress = csv.writer(f)
            progress.writerow(["iteration", "samples", "env_steps", "robot_return_mean", "wall_s"])
            while samples < args.timesteps:
                result = algo.train()
                iteration += 1
                runners = result["env_runners"]
                samples = int(sum(runners["num_agent_steps_sampled_lifetime"].values()))
                env_steps = int(runners["num_env_steps_sampled_lifetime"])
                # Per robot, as SB3's monitor counts it (RLlib's episode return sums the robots).
                returns = runners.get("agent_episode_returns_mean", {})
                ret = float(np.mean(list(returns.values()))) if returns else float("nan")
                wall_s = time.perf_counter() - start
                progress.writerow([iteration, samples, env_steps, ret, round(wall_s, 2)])
                f.flush()
                print(
                    f"iteration {iteration}: {samples} samples, return per robot {ret:.3f}, "
                    f"{wall_s:.0f} s"
                )
                if args.checkpoint_every and samples >= next_checkpoint:
                    algo.save_to_path(str(log_dir / "checkpoints" / f"samples_{samples}"))
                    next_checkpoint = samples + args.checkpoint_every
        checkpoint = log_dir / "checkpoint"
        algo.save_to_path(str(checkpoint))
        config.update(
            wall_s=time.perf_counter() - start,
            samples=samples,
            iterations=iteration,
            checkpoint=str(checkpoint),
            robot_return_mean=ret,
        )
        (log_dir / "config.json").write_text(json.dumps(config, indent=2) + "\n")
        trial_dir = Path(algo.logdir)
        algo.stop()
        with contextlib.suppress(OSError):
            trial_dir.rmdir()  # Ray's empty per-run folder under ~/ray_results
    print(
        f"trained {samples} samples in {config['wall_s']:.0f} s (seed {seed}); saved to {log_dir}"
    )
    return log_dir


def parse_override(text: str) -> tuple[str, Any]:
    """'key=value' with a Python literal value, for --hyperparams."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, ast.literal_eval(value)
    except (ValueError, SyntaxError) as err:
        raise argparse.ArgumentTypeError(f"{key}: not a Python literal: {value!r}") from err


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=Formatter)
    parser.add_argument(
        "--backend",
        choices=BACKENDS,
        default="sb3",
        help="sb3: this machine; rllib: PPO on a Ray cluster (shared view)",
    )
    parser.add_argument(
        "--ray-address",
        default=os.environ.get("RAY_ADDRESS"),
        help="Ray cluster (HOST:PORT) for --backend rllib, default $RAY_ADDRESS; none: a new "
        "local Ray instance",
    )
    parser.add_argument(
        "--env-runners",
        type=nonnegative_int,
        default=2,
        help="RLlib sampling actors (--backend rllib; 0: sample in the script's process)",
    )
    parser.add_argument("--algo", choices=sorted(ALGOS), default="ppo")
    parser.add_argument("--view", choices=VIEWS, default="shared")
    parser.add_argument(
        "--robots", type=int, default=2, help=f"robots holding the cargo, 1..{MAX_ROBOTS}"
    )
    parser.add_argument(
        "--timesteps",
        type=int,
        default=600_000,
        help="training length in samples, as SB3 counts them: one per robot per decision in the "
        "shared view (decisions = timesteps / robots, a decision being --action-repeat control "
        "steps), one per decision in the central view",
    )
    parser.add_argument("--copies", type=positive_int, default=2, help="environment copies")
    parser.add_argument(
        "--subprocess",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="run each copy in its own process",
    )
    parser.add_argument(
        "--seed", type=nonnegative_int, default=None, help="none: drawn and printed"
    )
    parser.add_argument("--log-dir", default="runs/ppo", help="run folder")
    parser.add_argument(
        "--estimates",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="observe the estimators' cargo estimates",
    )
    parser.add_argument(
        "--hidden-estimators",
        action="store_true",
        help="with --no-estimates: run the estimators, hidden from the policy (the peers' "
        "messages in the observation, which stay zero without the estimators, as evaluate.py "
        "shows them)",
    )
    parser.add_argument(
        "--task",
        choices=sorted(LEARNING_TASKS),
        default=None,
        help=f"the learning task (LEARNING_TASKS of astrocargo.envs.config); the flags below "
        f"override its entries; none: {DEFAULT_TASK}, with --backend rllib {RLLIB_TASK}",
    )
    parser.add_argument("--trajectory", default=None, choices=Trajectory.NAMES)
    parser.add_argument(
        "--max-cycles", type=positive_int, default=None, help="control steps per episode"
    )
    parser.add_argument("--noise", default=None, choices=sorted(NOISE_PROFILES))
    parser.add_argument("--control-hz", type=positive_float, default=None, help="env rate")
    parser.add_argument(
        "--action-repeat",
        type=positive_int,
        default=None,
        help="control steps per decision of the policy (DecisionEnv)",
    )
    parser.add_argument(
        "--residual-scale",
        type=nonnegative_float,
        default=0.0,
        help="> 0: residual policy, the env gets the scripted controller's action plus this "
        "times the policy's action (DecisionEnv); 0: the policy's action alone",
    )
    parser.add_argument(
        "--base-model",
        choices=BASE_MODELS,
        default="none",
        help="the residual's scripted controller: no cargo model, or each robot's live estimate "
        "(the estimators then run; --no-estimates hides them from the policy only)",
    )
    parser.add_argument(
        "--feedforward-obs",
        action="store_true",
        help="add to the policy's observation the thrust the cargo model adds to the scripted "
        "controller's feed-forward (astrocargo.agents.feedforward): from the live estimate, "
        "or with --no-estimates from the estimator's prior",
    )
    parser.add_argument(
        "--env",
        nargs="+",
        type=parse_override,
        metavar="KEY=VALUE",
        help="override the task's env arguments, values as Python literals "
        "(w_info=2.0 'cargo_mass_kg=(1.0, 20.0)')",
    )
    parser.add_argument("--torch-threads", type=positive_int, default=1)
    parser.add_argument(
        "--progress-bar", action=argparse.BooleanOptionalAction, default=True, help="SB3's bar"
    )
    parser.add_argument(
        "--hyperparams",
        nargs="+",
        type=parse_override,
        metavar="KEY=VALUE",
        help="override HYPERPARAMS entries, values as Python literals (gamma=0.98)",
    )
    parser.add_argument(
        "--checkpoint-every",
        type=nonnegative_int,
        default=0,
        help="save the model every N samples (0: no)",
    )
    parser.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="start PPO from a scripts/imitate.py run folder (its policy and normalisation; "
        "the same task and arm)",
    )
    parser.add_argument("--verbose", type=int, default=0)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, checked, with the run folder created: every error is the parser's,
    before anything is built."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.timesteps < 1:
        parser.error("--timesteps must be a positive integer")
    if not 1 <= args.robots <= MAX_ROBOTS:
        parser.error(f"--robots must be in 1..{MAX_ROBOTS}, got {args.robots}")
    try:
        check_decision_args(args.residual_scale, args.action_repeat or 1, args.base_model)
    except ValueError as err:
        parser.error(str(err))
    if args.base_model != "none" and not args.residual_scale:
        parser.error("--base-model is the residual's base controller: give --residual-scale > 0")
    if args.backend == "rllib":
        if args.algo != "ppo" or args.view != "shared":
            parser.error("--backend rllib trains PPO in the shared view only")
        if args.residual_scale or args.feedforward_obs or env_kwargs(args)["action_repeat"] != 1:
            parser.error(
                "--backend rllib trains on the bare env: no residual, no action repeat, "
                "no --feedforward-obs"
            )
        try:
            import_ray("--backend rllib needs Ray and RLlib")
        except ImportError as err:
            parser.error(str(err))
    if args.init_from is not None:
        check_init_from(parser, args)
    output_dir(parser, Path(args.log_dir), "--log-dir")
    return args


def check_init_from(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--init-from``: PPO, an imitation run of the same env arguments (parser error)."""
    path = args.init_from / "config.json"
    if args.algo != "ppo" or not path.is_file() or not (args.init_from / "model.zip").is_file():
        parser.error("--init-from needs --algo ppo and a run folder of scripts/imitate.py")
    theirs = policy_env(json.loads(path.read_text())["env_kwargs"])
    if theirs != policy_env(json.loads(json.dumps(env_kwargs(args)))):
        parser.error(f"--init-from {args.init_from}: trained on other env arguments")


def policy_env(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Env arguments as the policy sees them: whether the estimators run or are hidden from it
    (``observe_estimates``, ``hide_estimates``, ``estimators``) reduced to whether it observes
    them."""
    out = {k: v for k, v in kwargs.items() if k not in ("hide_estimates", "estimators")}
    out["observe_estimates"] = kwargs["observe_estimates"] and not kwargs["hide_estimates"]
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.backend == "rllib":
        train_rllib(args)
    else:
        train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
