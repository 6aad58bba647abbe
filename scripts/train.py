"""Train PPO or SAC on the Astrobee cargo env with Stable-Baselines3.

Two views of the multi-robot env:
- ``shared`` (default): one policy shared by all robots, each acting on its own observation
  (``SharedPolicyVecEnv``: every robot of every copy is one slot);
- ``central``: one policy sees all observations and sends all actions (``CentralizedCargoEnv``).

Observations and rewards are normalised with ``VecNormalize``. The run folder receives
``model.zip``, ``vecnormalize.pkl``, ``config.json`` (every setting, the seed, the wall time),
``monitor.csv`` (one row per finished episode of one robot or of the central agent) and
TensorBoard logs under ``tb/``. ``--timesteps`` counts samples as SB3 does: one per robot per
control step in the shared view (environment steps = timesteps / robots), one per control step
in the central view.

    python scripts/train.py --algo ppo --robots 2 --timesteps 600000 --copies 2 \\
        --seed 1 --checkpoint-every 50000 --log-dir runs/ppo_est
    python scripts/train.py ... --no-estimates --log-dir runs/ppo_noest
    tensorboard --logdir runs
"""

from __future__ import annotations

import argparse
import ast
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
from stable_baselines3 import PPO, SAC  # noqa: E402
from stable_baselines3.common.base_class import BaseAlgorithm  # noqa: E402
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback  # noqa: E402
from stable_baselines3.common.vec_env import (  # noqa: E402
    DummyVecEnv,
    SubprocVecEnv,
    VecEnv,
    VecMonitor,
    VecNormalize,
)

from astrocargo.envs.wrappers import (  # noqa: E402
    LEARNING_TASK,
    CentralizedCargoEnv,
    make_vec_env,
)

ALGOS = {"ppo": PPO, "sac": SAC}
VIEWS = ("shared", "central")
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
    """Keyword arguments of ``astrobee_cargo_v0.parallel_env`` for this run."""
    return {
        "n_robots": args.robots,
        "trajectory": args.trajectory,
        "noise": args.noise,
        "max_cycles": args.max_cycles,
        "control_hz": args.control_hz,
        "observe_estimates": args.estimates,
        # The estimators do not change the physics: without their outputs in the observation
        # they are only cost, so they are switched off (evaluate.py runs them, to score them).
        "estimators": args.estimates,
    }


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
    venv = VecNormalize(venv, norm_obs=True, norm_reward=True, gamma=hyper["gamma"])
    model = ALGOS[args.algo](
        "MlpPolicy",
        venv,
        seed=seed,
        verbose=args.verbose,
        tensorboard_log=None if log_dir is None else str(log_dir / "tb"),
        device="cpu",
        **hyper,
    )
    return model, hyper


def train(args: argparse.Namespace) -> tuple[BaseAlgorithm, Path]:
    """Train, save model, normalisation statistics and configuration; returns the model and
    the run folder."""
    seed = args.seed if args.seed is not None else int(np.random.default_rng().integers(2**31))
    print(f"seed {seed}")
    log_dir = Path(args.log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    model, hyper = build_model(args, seed, log_dir)
    config = {
        "algo": args.algo,
        "view": args.view,
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", choices=sorted(ALGOS), default="ppo")
    parser.add_argument("--view", choices=VIEWS, default="shared")
    parser.add_argument("--robots", type=int, default=2, help="robots holding the cargo, 1..4")
    parser.add_argument("--timesteps", type=int, default=600_000, help="samples (see above)")
    parser.add_argument("--copies", type=int, default=2, help="environment copies")
    parser.add_argument(
        "--subprocess",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="run each copy in its own process",
    )
    parser.add_argument("--seed", type=int, default=None, help="default: drawn and printed")
    parser.add_argument("--log-dir", default="runs/ppo", help="run folder")
    parser.add_argument(
        "--estimates",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="observe the estimators' cargo estimates",
    )
    parser.add_argument("--trajectory", default=LEARNING_TASK["trajectory"])
    parser.add_argument(
        "--max-cycles", type=int, default=LEARNING_TASK["max_cycles"], help="steps/episode"
    )
    parser.add_argument("--noise", default=LEARNING_TASK["noise"])
    parser.add_argument(
        "--control-hz", type=float, default=LEARNING_TASK["control_hz"], help="policy rate"
    )
    parser.add_argument("--torch-threads", type=int, default=1)
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
        "--checkpoint-every", type=int, default=0, help="save the model every N samples (0: no)"
    )
    parser.add_argument("--verbose", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("timesteps", "copies", "max_cycles", "torch_threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be a positive integer")
    if not 1 <= args.robots <= 4:
        parser.error("--robots must be in 1..4")
    train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
