"""Imitation of a scripted teacher by a residual policy, to initialise PPO (docs/learning.md).

Behaviour cloning then RL fine-tuning, the standard recipe when a good controller exists: the
teacher is the scripted cooperative controller with each robot's live estimate, the student a
residual on the no-model controller (``DecisionEnv`` with ``teacher_model="estimate"``). The
student's label at a decision is the held residual that makes its base the teacher,

    y = (1 / K) sum_k (clip(a_teacher(k), -1, 1) - a_base(k))[:6] / residual_scale,

over the decision's K control steps (``info["teacher_residual"]``). Data come from flights of
the teacher's correction held over each decision (``teacher_actor``), then from the student's
own flights, labelled by the teacher (DAgger: the states the student drifts to). The actor's
mean of SB3's ``MlpPolicy`` is fitted to y by mean squared error on the observation as
``VecNormalize`` normalises it; the critic to the discounted return of the normalised reward
(bootstrapped at the episode's end by the critic itself), so that PPO's first advantages are
not noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

Actor = Callable[[Any, dict[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass
class Flights:
    """Per sample (one robot, one decision): the policy's observation ``obs`` (raw, as the
    ``DecisionEnv`` gives it), the teacher's label ``label`` (6,), the decision's reward and
    ``track`` (a flight of one robot: samples of one track are consecutive, in time order)."""

    obs: list[np.ndarray] = field(default_factory=list)
    label: list[np.ndarray] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    track: list[int] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(obs (N, d), label (N, 6), reward (N,), track (N,)) as arrays."""
        return (
            np.asarray(self.obs, dtype=np.float64),
            np.asarray(self.label, dtype=np.float64),
            np.asarray(self.reward, dtype=np.float64),
            np.asarray(self.track, dtype=np.int64),
        )

    def extend(self, other: Flights) -> None:
        offset = max(self.track, default=-1) + 1
        self.obs += other.obs
        self.label += other.label
        self.reward += other.reward
        self.track += [t + offset for t in other.track]


def teacher_actor(env: Any, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The teacher's correction at the decision's first step, held (clipped to the action)."""
    del obs
    return {a: np.clip(r, -1.0, 1.0) for a, r in env.teacher_residual_now().items()}


def collect(env: Any, actor: Actor, seeds: list[int]) -> Flights:
    """One episode per seed of ``env`` (a ``DecisionEnv`` with a teacher) flown by ``actor``
    (env, policy observations -> residuals); every robot's decisions with their labels."""
    flights = Flights()
    for episode, seed in enumerate(seeds):
        obs, _ = env.reset(seed=seed)
        agents = list(env.possible_agents)
        while env.agents:
            acting = {a: obs[a] for a in env.agents}
            next_obs, rewards, _, _, infos = env.step(actor(env, acting))
            for a in acting:
                flights.obs.append(acting[a])
                flights.label.append(infos[a]["teacher_residual"])
                flights.reward.append(float(rewards[a]))
                flights.track.append(episode * len(agents) + agents.index(a))
            obs = next_obs
    return flights


def student_actor(model: Any, normalizer: Any) -> Actor:
    """The SB3 ``model``'s deterministic action from the normalised observation."""

    def act(env: Any, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        del env
        batch = normalizer.normalize_obs(np.stack(list(obs.values())))
        actions, _ = model.predict(batch, deterministic=True)
        return dict(zip(obs, np.asarray(actions, dtype=np.float64), strict=True))

    return act


def fit_regression(
    head: Callable[[torch.Tensor], torch.Tensor],
    params: list[torch.nn.Parameter],
    x: np.ndarray,
    y: np.ndarray,
    epochs: int,
    lr: float = 1e-3,
    batch_size: int = 256,
    seed: int = 0,
) -> list[float]:
    """Minimise the mean squared error of ``head(x)`` against ``y`` over ``params`` with Adam,
    ``epochs`` passes over shuffled minibatches; returns the full-data loss before and after
    each epoch."""
    gen = np.random.default_rng(seed)
    xt = torch.as_tensor(x, dtype=torch.float32)
    yt = torch.as_tensor(y, dtype=torch.float32).reshape(len(y), -1)
    optimizer = torch.optim.Adam(params, lr=lr)

    def full_loss() -> float:
        with torch.no_grad():
            return float(torch.mean((head(xt).reshape(yt.shape) - yt) ** 2))

    losses = [full_loss()]
    for _ in range(epochs):
        order = gen.permutation(len(x))
        for start in range(0, len(x), batch_size):
            idx = torch.as_tensor(order[start : start + batch_size])
            loss = torch.mean((head(xt[idx]).reshape(-1, yt.shape[1]) - yt[idx]) ** 2)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        losses.append(full_loss())
    return losses


def actor_mean(policy: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """The Gaussian's mean mu(obs) of SB3's ``ActorCriticPolicy`` (before the clip)."""
    return lambda obs: policy.action_net(
        policy.mlp_extractor.forward_actor(policy.extract_features(obs))
    )


def critic_value(policy: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """The value V(obs) of SB3's ``ActorCriticPolicy``."""
    return lambda obs: policy.value_net(
        policy.mlp_extractor.forward_critic(policy.extract_features(obs))
    )


def actor_params(policy: Any) -> list[torch.nn.Parameter]:
    return [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters()]


def critic_params(policy: Any) -> list[torch.nn.Parameter]:
    return [*policy.mlp_extractor.value_net.parameters(), *policy.value_net.parameters()]


def discounted_returns(
    reward: np.ndarray, track: np.ndarray, gamma: float, tail: np.ndarray | None = None
) -> np.ndarray:
    """G_t = r_t + gamma G_{t+1} along each track, G after its last sample = ``tail`` of that
    sample (bootstrap; zero if None)."""
    out = np.empty_like(reward)
    following = 0.0
    for t in range(len(reward) - 1, -1, -1):
        last = t == len(reward) - 1 or track[t + 1] != track[t]
        if last:
            following = 0.0 if tail is None else float(tail[t])
        following = reward[t] + gamma * following
        out[t] = following
    return out


def running_returns(reward: np.ndarray, track: np.ndarray, gamma: float) -> np.ndarray:
    """VecNormalize's return statistic: R_t = gamma R_{t-1} + r_t from each track's start."""
    out = np.empty_like(reward)
    running = 0.0
    for t in range(len(reward)):
        if t == 0 or track[t] != track[t - 1]:
            running = 0.0
        running = gamma * running + reward[t]
        out[t] = running
    return out


def fit_normalizer(normalizer: Any, obs: np.ndarray, reward: np.ndarray, track: np.ndarray) -> None:
    """Set ``VecNormalize``'s observation and return statistics from the flights (as its running
    updates would after these samples)."""
    normalizer.obs_rms.update(obs)
    normalizer.ret_rms.update(running_returns(reward, track, normalizer.gamma))


def fit_critic(
    policy: Any, normalizer: Any, flights: Flights, epochs: int, rounds: int = 3
) -> list[float]:
    """Fit V to the discounted return of the normalised reward, the tail after each track's
    last sample bootstrapped by V there (``rounds`` times: returns, fit, returns, ...); the
    losses of the last fit. Known bias: each round adds one discounted step to the tail, so a
    few rounds leave the values of a track's last ~1 / (1 - gamma) samples too small against
    the infinite-horizon value PPO bootstraps at a time limit (docs/learning.md)."""
    obs, _, reward, track = flights.arrays()
    x = normalizer.normalize_obs(obs)
    r = normalizer.normalize_reward(reward)
    value, losses = critic_value(policy), []
    for _ in range(rounds):
        with torch.no_grad():
            tail = value(torch.as_tensor(x, dtype=torch.float32)).numpy().ravel()
        target = discounted_returns(r, track, normalizer.gamma, tail)
        losses = fit_regression(value, critic_params(policy), x, target, epochs)
    return losses


def set_log_std(policy: Any, log_std: float) -> None:
    """The Gaussian's log standard deviation, every action entry (PPO's exploration)."""
    with torch.no_grad():
        policy.log_std.fill_(log_std)


def initialise_from(model: Any, run_dir: Any) -> None:
    """Start ``model`` (PPO on a ``VecNormalize``) from an imitation run folder: its policy's
    weights (actor, critic, log std) and its observation and return statistics."""
    import pickle
    from pathlib import Path

    from stable_baselines3 import PPO

    run_dir = Path(run_dir)
    source = PPO.load(run_dir / "model.zip", device="cpu")
    model.policy.load_state_dict(source.policy.state_dict())
    with open(run_dir / "vecnormalize.pkl", "rb") as f:
        stats = pickle.load(f)
    venv = model.get_env()
    venv.obs_rms, venv.ret_rms = stats.obs_rms.copy(), stats.ret_rms.copy()
