"""Initialise a residual PPO policy by imitating the scripted controller with live estimates.

Behaviour cloning with DAgger (``astrocargo.agents.imitation``): flights of the teacher's
correction held over each decision, labelled per decision with the residual that makes the
no-model base the teacher; then ``--dagger-rounds`` rounds of the student's own flights, labelled
by the teacher; the actor's mean fitted by MSE after each, the critic to the normalised
discounted return of the last flights. The run folder holds what ``scripts/train.py`` saves
(``model.zip``, ``vecnormalize.pkl``, ``config.json``): ``evaluate.py`` scores it as it is and
``train.py --init-from RUN`` fine-tunes it with PPO. Flags are ``train.py``'s (the same
network, task and arm: ``--feedforward-obs``, ``--no-estimates``), plus those below. Seeds of
the flights: 100000 + 1000 * seed + k (the evaluation uses 1000-1003 per bin).

    .venv/bin/python scripts/imitate.py --task cargo --residual-scale 1.0 --feedforward-obs \\
        --seed 1 --episodes 16 --dagger-rounds 1 --dagger-episodes 8 --log-dir runs/bc_est_1
    .venv/bin/python scripts/train.py --task cargo --residual-scale 1.0 --feedforward-obs \\
        --seed 1 --init-from runs/bc_est_1 --timesteps 100000 --log-dir runs/bcft_est_1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling train.py, cli.py
import train  # noqa: E402
from cli import nonnegative_int, output_dir, positive_int  # noqa: E402

from astrocargo.agents import imitation  # noqa: E402
from astrocargo.envs.decision import make_cargo_env  # noqa: E402

FLIGHT_SEED_BASE = 100_000  # far from the evaluation's episodes (seed 1000 + k)


def build_parser() -> argparse.ArgumentParser:
    parser = train.build_parser()
    parser.description = __doc__.splitlines()[0]
    group = parser.add_argument_group("imitation")
    group.add_argument("--episodes", type=positive_int, default=16, help="teacher flights")
    group.add_argument("--dagger-rounds", type=nonnegative_int, default=1)
    group.add_argument(
        "--dagger-episodes", type=positive_int, default=8, help="student flights per round"
    )
    group.add_argument("--fit-epochs", type=positive_int, default=40, help="passes per fit")
    group.add_argument("--fit-lr", type=float, default=1e-3, help="Adam's learning rate")
    group.add_argument(
        "--log-std", type=float, default=-2.5, help="the policy's log std after the fit"
    )
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.algo != "ppo" or args.view != "shared" or args.backend != "sb3":
        parser.error("imitation initialises SB3's PPO in the shared view")
    if not args.residual_scale or args.base_model != "none":
        parser.error("imitation trains a residual (--residual-scale > 0) on the no-model base")
    output_dir(parser, Path(args.log_dir), "--log-dir")
    return args


def flight_env(args: argparse.Namespace):
    """The run's ``DecisionEnv`` with the teacher beside it: the estimators run (the teacher
    reads them) and, with ``--no-estimates``, are hidden from the policy."""
    kwargs = train.env_kwargs(args)
    kwargs.update(
        observe_estimates=True,
        estimators=True,
        hide_estimates=not args.estimates,
        teacher_model="estimate",
    )
    return make_cargo_env(**kwargs)


def fit_actor(model, normalizer, flights: imitation.Flights, args) -> list[float]:
    obs, label, _, _ = flights.arrays()
    x = normalizer.normalize_obs(obs)
    y = np.clip(label, -1.0, 1.0)  # the action space
    policy = model.policy
    return imitation.fit_regression(
        imitation.actor_mean(policy),
        imitation.actor_params(policy),
        x,
        y,
        args.fit_epochs,
        lr=args.fit_lr,
        seed=args.seed,
    )


def seeds(args: argparse.Namespace, start: int, count: int) -> list[int]:
    return [FLIGHT_SEED_BASE + 1000 * args.seed + start + k for k in range(count)]


def imitate(args: argparse.Namespace) -> Path:
    """Collect, fit, save; returns the run folder."""
    args.seed = 0 if args.seed is None else args.seed
    log_dir = Path(args.log_dir)
    start = time.perf_counter()
    model, hyper = train.build_model(args, args.seed, None)
    normalizer = model.get_env()
    env = flight_env(args)
    flights = imitation.collect(env, imitation.teacher_actor, seeds(args, 0, args.episodes))
    obs, _, reward, track = flights.arrays()
    imitation.fit_normalizer(normalizer, obs, reward, track)
    history = [fit_actor(model, normalizer, flights, args)]
    last = flights
    for k in range(args.dagger_rounds):
        first = args.episodes + k * args.dagger_episodes
        actor = imitation.student_actor(model, normalizer)
        last = imitation.collect(env, actor, seeds(args, first, args.dagger_episodes))
        flights.extend(last)
        history.append(fit_actor(model, normalizer, flights, args))
    imitation.set_log_std(model.policy, args.log_std)
    critic = imitation.fit_critic(model.policy, normalizer, last, args.fit_epochs)
    wall_s = time.perf_counter() - start
    model.save(log_dir / "model.zip")
    normalizer.save(str(log_dir / "vecnormalize.pkl"))
    config = {
        "algo": "ppo",
        "view": "shared",
        "task": train.task_name(args),
        "seed": args.seed,
        "timesteps": 0,
        "samples": 0,
        "copies": args.copies,
        "env_kwargs": train.env_kwargs(args),
        "hyperparams": hyper,
        "imitation": {
            "teacher": "scripted, live estimate",
            "episodes": args.episodes,
            "dagger_rounds": args.dagger_rounds,
            "dagger_episodes": args.dagger_episodes,
            "flight_seeds": seeds(
                args, 0, args.episodes + args.dagger_rounds * args.dagger_episodes
            ),
            "labelled_samples": len(flights.obs),
            "fit_epochs": args.fit_epochs,
            "fit_lr": args.fit_lr,
            "log_std": args.log_std,
            "actor_mse": [[h[0], h[-1]] for h in history],
            "critic_mse": [critic[0], critic[-1]],
        },
        "wall_s": wall_s,
        "command": " ".join(sys.argv),
    }
    (log_dir / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    print(
        f"imitation: {len(flights.obs)} labelled samples, actor MSE per fit "
        f"{[f'{h[0]:.4f}->{h[-1]:.4f}' for h in history]}, {wall_s:.0f} s; saved to {log_dir}"
    )
    return log_dir


def main(argv: list[str] | None = None) -> int:
    imitate(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
