"""The parallel env as a learned policy sees it: decisions, residual actions, hidden estimates.

- ``DecisionEnv``: one decision every ``action_repeat`` control steps, optionally a residual added
  to the thrust of the scripted controller with no cargo model or with the live estimate
  (``u = u_base + residual_scale * u_policy`` on the six thrust entries, in the action's
  normalised units, which the env clips to [-1, 1]), optionally with the estimates hidden from
  the policy, optionally with the cargo model's feed-forward as an input
  (``agents/feedforward.py``).
- ``cargo_env_fn(residual_scale=..., action_repeat=..., base_model=..., hide_estimates=...,
  feedforward_obs=...)``: a picklable factory of it (or of the plain parallel env at the
  defaults), what ``SharedPolicyVecEnv`` copies and the training scripts build.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from astrocargo.agents.feedforward import (
    FEEDFORWARD_DIM,
    FEEDFORWARD_SOURCES,
    FeedForwardObservation,
)
from astrocargo.envs.observations import ESTIMATE_BLOCKS


def cargo_env_fn(**kwargs: Any) -> Callable[[], ParallelEnv]:
    """A picklable factory of ``make_cargo_env(**kwargs)``: the decision arguments
    (``residual_scale``, ``action_repeat``, ``base_model``, ``hide_estimates``,
    ``feedforward_obs``, ``teacher_model``) and those of ``astrobee_cargo_v0.parallel_env``."""
    return functools.partial(make_cargo_env, **kwargs)


def make_cargo_env(
    residual_scale: float = 0.0,
    action_repeat: int = 1,
    base_model: str = "none",
    hide_estimates: bool = False,
    feedforward_obs: str | None = None,
    teacher_model: str | None = None,
    **env_kwargs: Any,
) -> ParallelEnv:
    """What ``cargo_env_fn`` builds, made now: the parallel env, wrapped in ``DecisionEnv`` unless
    the decision arguments are the defaults."""
    from astrocargo.envs import astrobee_cargo_v0

    env = astrobee_cargo_v0.parallel_env(**env_kwargs)
    decision = (
        residual_scale,
        action_repeat,
        base_model,
        hide_estimates,
        feedforward_obs,
        teacher_model,
    )
    if decision != (0.0, 1, "none", False, None, None):
        return DecisionEnv(env, *decision)
    return env


RESIDUAL_DIM = 6  # a residual acts on the thrust entries of the action (force, torque)


def residual_actions(base: np.ndarray, residual: np.ndarray, residual_scale: float) -> np.ndarray:
    """The action sent to the env: thrust entries a_env[:6] = a_base[:6] + residual_scale * a,
    the arm targets a_env[6:] = a_base[6:] (``base`` (..., 8), ``residual`` (..., 6); the env
    then clips each entry to [-1, 1])."""
    out = np.array(base, dtype=np.float64)
    out[..., :RESIDUAL_DIM] += residual_scale * np.asarray(residual, dtype=np.float64)
    return out


def teacher_residual(teacher: np.ndarray, base: np.ndarray, residual_scale: float) -> np.ndarray:
    """The residual that makes the base controller's action the teacher's on the thrust entries:
    r = (clip(a_teacher, -1, 1) - a_base)[..., :6] / residual_scale (``teacher``, ``base``
    (..., 8), in the action's normalised units; the env clips what it is sent to [-1, 1], so
    the teacher's action is taken as the env applies it)."""
    target = np.clip(np.asarray(teacher, dtype=np.float64), -1.0, 1.0)[..., :RESIDUAL_DIM]
    return (target - np.asarray(base, dtype=np.float64)[..., :RESIDUAL_DIM]) / residual_scale


# The cargo models a residual's base controller may use (``ObservationController``'s).
BASE_MODELS = ("none", "estimate")


def check_decision_args(
    residual_scale: Any, action_repeat: Any, base_model: str = "none"
) -> tuple[float, int]:
    """``residual_scale`` a number >= 0, ``action_repeat`` a positive integer, ``base_model``
    one of ``BASE_MODELS`` (ValueError)."""
    check_cargo_model("base_model", base_model)
    scale = float(residual_scale)
    if not np.isfinite(scale) or scale < 0.0:
        raise ValueError(f"residual_scale must be a number >= 0, got {residual_scale!r}")
    if isinstance(action_repeat, bool) or not isinstance(action_repeat, int | np.integer):
        raise ValueError(f"action_repeat must be a positive integer, got {action_repeat!r}")
    if action_repeat < 1:
        raise ValueError(f"action_repeat must be a positive integer, got {action_repeat!r}")
    return scale, int(action_repeat)


def check_cargo_model(name: str, model: str) -> None:
    """``model`` one of ``BASE_MODELS`` (ValueError naming the argument ``name``)."""
    if model not in BASE_MODELS:
        raise ValueError(f"{name} must be one of {BASE_MODELS}, got {model!r}")


def policy_observation_index(layout: dict[str, slice], hide_estimates: bool) -> np.ndarray:
    """Indices of the env's observation (``layout``: ``sim.obs_layout``) that a policy sees:
    all, or with ``hide_estimates`` all but the estimate blocks (ValueError if there are none)."""
    index = np.arange(layout["all"].stop)
    if not hide_estimates:
        return index
    if "estimate_mean" not in layout:
        raise ValueError("hide_estimates needs an env that observes the estimates")
    hidden = np.concatenate([index[layout[name]] for name, _ in ESTIMATE_BLOCKS])
    return np.setdiff1d(index, hidden)


def check_feedforward_obs(source: str | None, layout: dict[str, slice]) -> str | None:
    """``source`` None or one of ``FEEDFORWARD_SOURCES``; "estimate" needs an env that
    observes the estimates (ValueError)."""
    if source is not None and source not in FEEDFORWARD_SOURCES:
        raise ValueError(f"feedforward_obs must be None or one of {FEEDFORWARD_SOURCES}")
    if source == "estimate" and "estimate_mean" not in layout:
        raise ValueError('feedforward_obs="estimate" needs an env that observes the estimates')
    return source


class DecisionEnv(ParallelEnv):
    """The env as a learned policy sees it: one decision every ``action_repeat`` control steps,
    optionally a residual on top of the scripted controller, optionally without the estimates.

    Each control step k of a decision's ``action_repeat`` steps sends robot i

        residual_scale > 0:  a_env,i(k)[:6] = a_base,i(k)[:6] + residual_scale * a_i,
                             a_env,i(k)[6:] = a_base,i(k)[6:]
        residual_scale = 0:  a_env,i(k) = a_i

    with a_i the policy's action, held over the decision: with a residual a_i in [-1, 1]^6 acts
    on the thrust (force, torque; the action space is then 6-dimensional) and the arm targets
    are the scripted controller's (noise on the arm targets swings the arms and, with them, the
    grasp: a residual of std 0.02 on all eight entries multiplied the cargo's position error by
    five, docs/learning.md); without, a_i in [-1, 1]^8 is the whole action. a_base,i(k) is the
    action of ``ObservationController`` with ``cargo_model=base_model`` from the observation of
    step k: "none" (the cooperative controller that models the robots only, no cargo) or
    "estimate" (the cargo from each robot's live estimate; the env must observe the estimates).
    The scripted feedback runs at the control rate, the residual at the decision rate. The env
    clips each entry to [-1, 1]. Zero residual actions are the base controller. The controller
    reads only the observation, never the truth.

    ``hide_estimates``: the policy's observation is the env's without the estimate blocks
    (``estimate_mean``, ``estimate_std``), while the base controller still reads them: the
    ablation of what observing the estimates adds to a residual on the "estimate" base.

    ``feedforward_obs`` "estimate" or "prior": the policy's observation ends with six more
    entries, robot i's u_ff,i, the thrust (fractions of its limits, its base frame: the
    residual's units) that the cargo model adds to the scripted controller's feed-forward
    (``astrocargo.agents.feedforward``) with its live estimate ("estimate") or the estimator's
    prior ("prior": the same form without the cargo's information), from the decision's
    observation.

    ``teacher_model`` (needs a residual): the scripted controller with that cargo model
    ("estimate": the live estimate) runs beside the base as a teacher for imitation
    (``astrocargo.agents.imitation``): each agent's info gets ``teacher_residual``, the mean
    over the decision's control steps of ``teacher_residual(a_teacher(k), a_base(k))``, the
    held residual that comes closest (least squares) to making the base the teacher along the
    flight actually flown; ``teacher_residual_now()`` gives it from the last observation alone.

    A decision returns the last step's observations, terminations, truncations and infos and
    the sum of its steps' rewards; it ends early when the episode ends. Each agent's info gets
    ``decision_steps`` (control steps made), ``saturated_mean`` (the mean of ``saturated`` over
    them) and, with a residual, ``base_action`` (a_base of the last step). ``max_cycles`` of
    the wrapped env counts control steps: an episode has max_cycles / action_repeat decisions.
    """

    def __init__(
        self,
        env: ParallelEnv,
        residual_scale: float = 0.0,
        action_repeat: int = 1,
        base_model: str = "none",
        hide_estimates: bool = False,
        feedforward_obs: str | None = None,
        teacher_model: str | None = None,
    ):
        self.residual_scale, self.action_repeat = check_decision_args(
            residual_scale, action_repeat, base_model
        )
        if teacher_model is not None:
            check_cargo_model("teacher_model", teacher_model)
            if not self.residual_scale:
                raise ValueError("teacher_model needs a residual (residual_scale > 0)")
        self.base_model, self.teacher_model = base_model, teacher_model
        self.teacher: Any = None
        self.feedforward_obs = check_feedforward_obs(feedforward_obs, env.sim.obs_layout)
        self.feedforward: Any = None
        self.env = env
        self.possible_agents = list(env.possible_agents)
        self.metadata = env.metadata
        self.render_mode = env.render_mode
        self.controller: Any = None
        self._obs: dict[str, np.ndarray] = {}
        self._residual_space = spaces.Box(-1.0, 1.0, (RESIDUAL_DIM,), np.float32)
        self.policy_obs = policy_observation_index(env.sim.obs_layout, hide_estimates)
        space = env.observation_space(self.possible_agents[0])
        extra = FEEDFORWARD_DIM if self.feedforward_obs else 0
        self._obs_space = spaces.Box(
            np.concatenate([space.low[self.policy_obs], np.full(extra, -np.inf)]),
            np.concatenate([space.high[self.policy_obs], np.full(extra, np.inf)]),
            dtype=space.dtype,
        )

    @property
    def agents(self) -> list[str]:
        return self.env.agents

    @property
    def sim(self) -> Any:
        """The wrapped env's ``CargoTransport``."""
        return self.env.sim

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_") or name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)  # max_cycles, ... of the wrapped env

    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space:
        space = self.env.action_space(agent)
        return self._residual_space if self.residual_scale else space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        from astrocargo.agents.controllers import ObservationController

        obs, infos = self.env.reset(seed=seed, options=options)
        if self.residual_scale:
            self.controller = ObservationController.for_env(self.env, self.base_model)
        if self.teacher_model:
            self.teacher = ObservationController.for_env(self.env, self.teacher_model)
        if self.feedforward_obs:
            self.feedforward = FeedForwardObservation(self.env, self.feedforward_obs)
        self._obs = obs
        return self._policy_view(obs), infos

    def _policy_view(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not self.feedforward_obs:
            return {a: o[self.policy_obs] for a, o in obs.items()}
        # The robots holding the cargo (all of them in the final observation of an episode);
        # a robot that has let go gets zeros.
        u_ff = self.feedforward({a: obs[a] for a in self.env.agents} or obs)
        none = np.zeros(FEEDFORWARD_DIM)
        return {a: np.concatenate([o[self.policy_obs], u_ff.get(a, none)]) for a, o in obs.items()}

    def base_actions(self) -> dict[str, np.ndarray]:
        """a_base of every live agent from the last observation (zeros without a residual)."""
        live = {a: self._obs[a] for a in self.env.agents}
        if not self.residual_scale:
            return {a: np.zeros(8) for a in live}
        return self.controller.predict(live)[0] if live else {}

    def teacher_residual_now(self, base: dict[str, np.ndarray] | None = None) -> dict:
        """agent -> ``teacher_residual`` (6,) of every live agent from the last observation
        (``base``: ``base_actions()`` if already computed)."""
        live = {a: self._obs[a] for a in self.env.agents}
        if not live:
            return {}
        base = self.base_actions() if base is None else base
        teacher = self.teacher.predict(live)[0]
        return {a: teacher_residual(teacher[a], base[a], self.residual_scale) for a in live}

    def step(self, actions: dict[str, np.ndarray]) -> tuple:
        total = dict.fromkeys(self.possible_agents, 0.0)
        saturated = dict.fromkeys(self.possible_agents, 0.0)
        labels = {a: np.zeros(RESIDUAL_DIM) for a in self.possible_agents}
        steps = 0
        while True:
            base = self.base_actions()
            if self.teacher is not None:
                for a, r in self.teacher_residual_now(base).items():
                    labels[a] += r
            if self.residual_scale:
                sent = {
                    a: residual_actions(base[a], actions[a], self.residual_scale)
                    for a in self.env.agents
                }
            else:
                sent = {a: actions[a] for a in self.env.agents}
            obs, rewards, terms, truncs, infos = self.env.step(sent)
            self._obs = obs
            steps += 1
            for a, r in rewards.items():
                total[a] += float(r)
                saturated[a] += float(infos[a].get("saturated", 0.0))
            ended = any(terms[a] or truncs[a] for a in rewards)
            if ended or steps == self.action_repeat:
                break
        for a, info in infos.items():
            info["decision_steps"] = steps
            info["saturated_mean"] = saturated[a] / steps
            if self.residual_scale and a in base:
                info["base_action"] = base[a]
            if self.teacher is not None:
                info["teacher_residual"] = labels[a] / steps
        return self._policy_view(obs), {a: total[a] for a in rewards}, terms, truncs, infos

    def render(self) -> Any:
        return self.env.render()

    def state(self) -> np.ndarray:
        return self.env.state()

    def close(self) -> None:
        self.env.close()
