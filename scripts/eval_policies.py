"""The policies ``evaluate.py`` scores, and how a policy is named on its command line.

Each policy has ``name``, ``observe_estimates``, ``trajectory`` (None: the task's), ``decision``
(what the episode records of how it decides), ``reset(env)`` at the start of each episode and
``act(obs)``: the actions (n_robots, 8) from the env's observations (n_robots, obs_dim) at the
env's control rate. ``make_policy(spec, cargo_model)`` builds one from its command-line name.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np

from astrocargo.agents.controllers import CARGO_MODELS, ObservationController
from astrocargo.agents.excitation import is_trajectory_name, trajectory_choices
from astrocargo.agents.feedforward import FeedForwardObservation
from astrocargo.envs.config import LEARNING_TASKS

DEFAULT_TASK = "cargo"
POLICY_HELP = (
    "'zero', 'scripted' or a run folder of scripts/train.py (with model.zip and config.json), "
    "or 'feedforward'; 'scripted:MODEL@TRAJECTORY' picks the cargo model (estimate, none, "
    "truth) and trajectory; 'feedforward': the no-model controller plus u_ff of the live "
    "estimate, held ('feedforward:prior': of the estimator's prior); 'teacher': the no-model "
    "controller plus the live-estimate correction, held (the imitation's oracle); "
    "'RUN@SAMPLES': the run's checkpoint after SAMPLES samples"
)


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


def checkpoint_samples(run_dir: Path) -> list[int]:
    """Sample counts of a run's checkpoints (train.py --checkpoint-every), ascending."""
    names = (run_dir / "checkpoints").glob("rl_model_*_steps.zip")
    return sorted(int(p.stem.split("_")[-2]) for p in names)
