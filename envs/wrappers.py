"""Adapters from the PettingZoo cargo env to Stable-Baselines3 and Gymnasium.

- ``SharedPolicyVecEnv``: an SB3 ``VecEnv`` with parameter sharing. Every robot of every copy of
  the parallel env is one slot (slot ``c * n_robots + i`` is robot ``i`` of copy ``c``), so one
  policy acts for all robots from their local observations. Copies run in this process or, with
  ``subprocess=True``, one subprocess each. An episode ends for all robots of a copy at once;
  the copy then resets itself and each of its slots reports ``terminal_observation`` and
  ``TimeLimit.truncated`` (True at ``max_cycles``, False on termination), so SB3 bootstraps
  the value at the time limit only. ``seed(s)`` gives copy ``c`` the seed ``s + c`` at the next
  reset; later episodes continue each copy's own generator, so a run is reproducible. A copy
  that is the bare cargo env steps through ``AstrobeeCargoEnv.step_arrays`` (no dicts); any
  other parallel env (``DecisionEnv`` ...) through its ``step``.
- ``SlotController``: runs a controller that acts on one copy's observations (n_robots, obs_dim)
  (e.g. ``ObservationController``) on all the slots of a ``SharedPolicyVecEnv``.
- ``DecisionEnv`` and ``cargo_env_fn`` (the env as a learned policy sees it, and the picklable
  factory every copy is built by) live in ``astrocargo.envs.decision``.
- ``fast_inference``: SB3's ``predict`` without its per-call overhead, the same actions.
- ``fast_normalization``: a ``VecNormalize``'s running statistics as ``CompiledRunningMeanStd``,
  SB3's class updated by one compiled kernel to the same numbers.
- ``CentralizedCargoEnv``: a single-agent ``gymnasium.Env`` in which one policy drives all robots:
  the observation is the robots' observations concatenated in agent order, the action the robots'
  actions concatenated, the reward the robots' mean reward. Registered as ``ENV_ID``
  (``astrocargo/AstrobeeCargo-v0``) when ``astrocargo.envs`` is imported;
  ``gymnasium.make("astrocargo.envs:" + ENV_ID)`` imports the package and makes it in one call
  (``"astrocargo.envs.wrappers:" + ENV_ID`` works too).

SuperSuit's vector path (``pettingzoo_env_to_vec_env_v1`` then ``concat_vec_envs_v1``) also
works: the env deep-copies and pickles (a live renderer is not copied), which that path needs to
build its copies. It is not used here because of its known limits with SB3 2.9 (SuperSuit 3.11):
truncation at ``max_cycles`` is reported as termination (no ``TimeLimit.truncated``, so SB3 does
not bootstrap the value at the time limit); ``ConcatVecEnv`` has no ``seed``, so passing
``seed=`` to an SB3 algorithm fails; and every copy starts from the same deep copy, so without
explicit per-copy seeds the copies run identical episodes. ``SharedPolicyVecEnv`` reports
truncation, seeds copy ``c`` with ``s + c`` and implements ``seed``.
"""

from __future__ import annotations

import copy
import functools
import multiprocessing as mp
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from numba import njit
from pettingzoo import ParallelEnv
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env.base_vec_env import (
    CloudpickleWrapper,
    VecEnv,
    VecEnvIndices,
    VecEnvStepReturn,
)

from astrocargo.envs import ENV_ID  # noqa: F401  (registered by astrocargo/envs/__init__.py)
from astrocargo.envs.cargo_transport import AstrobeeCargoEnv
from astrocargo.envs.config import LEARNING_TASKS
from astrocargo.envs.decision import cargo_env_fn, make_cargo_env

# The task of the training benchmark (scripts/benchmark_performance.py).
LEARNING_TASK: dict[str, Any] = LEARNING_TASKS["figure8_10s"]


# --------------------------------------------------------------------------- one copy


class _Copy:
    """One parallel env seen as arrays in agent order, resetting itself when its episode ends."""

    def __init__(self, env: ParallelEnv) -> None:
        self.env = env
        self.agents = list(env.possible_agents)
        # The cargo env's array step (``AstrobeeCargoEnv.step_arrays``): no dicts on the way. Not
        # through a wrapper (``DecisionEnv`` passes attributes through: its own step must run).
        self._step_arrays = env.step_arrays if isinstance(env, AstrobeeCargoEnv) else None

    def reset(self, seed: int | None, options: dict | None) -> tuple[np.ndarray, list[dict]]:
        obs, infos = self.env.reset(seed=seed, options=options or None)
        return self._stack(obs), [dict(infos.get(a, {})) for a in self.agents]

    def step(self, actions: np.ndarray) -> tuple:
        """Returns obs (n, d), rewards (n,) float32, dones (n,), infos and the reset infos."""
        if self._step_arrays is not None:
            # Its infos are built anew at every step: they are ours to extend.
            r = self._step_arrays(actions)
            obs_array, rewards, infos = r.observations, r.rewards, r.infos
            terminated, truncated = r.terminated.tolist(), r.truncated.tolist()
        else:
            obs_array, rewards, terminated, truncated, infos = self._step_dicts(actions)
        # On Python lists: numpy's logical_or, any and all on lists of two cost more.
        done = [t or u for t, u in zip(terminated, truncated)]  # noqa: B905 (both per agent)
        if any(done) and not all(done):
            raise RuntimeError(
                "SharedPolicyVecEnv needs episodes that end for all agents at once; agents "
                f"{[a for a, d in zip(self.agents, done, strict=True) if not d]} are still running"
            )
        dones = np.array(done)
        reset_infos = [{} for _ in self.agents]
        if done[0]:
            for i, info in enumerate(infos):
                info["terminal_observation"] = obs_array[i]
                info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            obs_array, reset_infos = self.reset(None, None)
        return obs_array, rewards.astype(np.float32), dones, infos, reset_infos

    def _step_dicts(self, actions: np.ndarray) -> tuple:
        """A step of any parallel env: obs (n, d), rewards (n,), terminated and truncated (lists
        of n) and copies of the infos, in agent order."""
        agents = self.agents
        # One action row per agent (SharedPolicyVecEnv splits them so): zip's strict check
        # would cost more than the dict.
        obs, rewards, terms, truncs, infos = self.env.step(dict(zip(agents, actions)))  # noqa: B905
        return (
            self._stack(obs), np.array([rewards[a] for a in agents]),
            [bool(terms[a]) for a in agents], [bool(truncs[a]) for a in agents],
            [dict(infos[a]) for a in agents],
        )  # fmt: skip

    def _stack(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The agents' observations as rows (n, d), in agent order."""
        return np.array([obs[a] for a in self.agents])


def _worker(remote: Any, parent_remote: Any, env_fn: CloudpickleWrapper) -> None:
    """Subprocess loop: one copy, commands (name, data) from the pipe."""
    parent_remote.close()
    copy = _Copy(env_fn.var())
    try:
        while True:
            cmd, data = remote.recv()
            if cmd == "step":
                remote.send(copy.step(data))
            elif cmd == "reset":
                remote.send(copy.reset(*data))
            elif cmd == "render":
                remote.send(copy.env.render())
            elif cmd == "get_attr":
                remote.send(getattr(copy.env, data))
            elif cmd == "set_attr":
                remote.send(setattr(copy.env, data[0], data[1]))
            elif cmd == "env_method":
                remote.send(getattr(copy.env, data[0])(*data[1], **data[2]))
            elif cmd == "close":
                copy.env.close()
                remote.close()
                break
            else:
                raise NotImplementedError(f"unknown command {cmd!r}")
    except (EOFError, KeyboardInterrupt):
        pass


# --------------------------------------------------------------------------- VecEnv


class SharedPolicyVecEnv(VecEnv):
    """SB3 ``VecEnv`` over ``n_copies`` copies of a parallel env, one slot per robot per copy.

    ``env_fn`` makes one copy (picklable when ``subprocess=True``: ``cargo_env_fn(**kwargs)``).
    All agents must share one observation space and one action space (parameter sharing).
    ``start_method`` is a ``multiprocessing`` start method; the default, "forkserver" where
    available, is safe with torch's threads but needs the usual ``if __name__ == "__main__"``.
    """

    def __init__(
        self,
        env_fn: Callable[[], ParallelEnv],
        n_copies: int = 1,
        subprocess: bool = False,
        start_method: str | None = None,
    ) -> None:
        if isinstance(n_copies, bool) or not isinstance(n_copies, int) or n_copies < 1:
            raise ValueError(f"n_copies must be a positive integer, got {n_copies!r}")
        self.n_copies = n_copies
        self.subprocess = bool(subprocess)
        self.closed = False
        self._actions: np.ndarray | None = None
        first = env_fn()
        agents = list(first.possible_agents)
        obs_space = first.observation_space(agents[0])
        act_space = first.action_space(agents[0])
        for agent in agents[1:]:
            same = first.observation_space(agent) == obs_space
            if not same or first.action_space(agent) != act_space:
                raise ValueError(
                    f"parameter sharing needs identical spaces for all agents; {agent!r} differs "
                    f"from {agents[0]!r}"
                )
        self.n_robots = len(agents)
        self.possible_agents = agents
        if self.subprocess:
            first.close()
            if start_method is None:
                methods = mp.get_all_start_methods()
                start_method = "forkserver" if "forkserver" in methods else "spawn"
            ctx = mp.get_context(start_method)
            pipes = [ctx.Pipe() for _ in range(n_copies)]
            self.remotes = [parent for parent, _ in pipes]
            self.processes = []
            for parent, child in pipes:
                process = ctx.Process(
                    target=_worker, args=(child, parent, CloudpickleWrapper(env_fn)), daemon=True
                )
                process.start()
                self.processes.append(process)
                child.close()
        else:
            self.copies = [_Copy(first)] + [_Copy(env_fn()) for _ in range(n_copies - 1)]
        self._copy_seeds: list[int | None] = [None] * n_copies
        super().__init__(n_copies * self.n_robots, obs_space, act_space)

    # ------------------------------------------------------------------ slots <-> copies
    def _split(self, per_slot: np.ndarray) -> np.ndarray:
        return np.asarray(per_slot).reshape(self.n_copies, self.n_robots, *np.shape(per_slot)[1:])

    def _call_all(self, cmd: str, per_copy: Sequence[Any]) -> list[Any]:
        """Run ``cmd`` on every copy with its own data; results in copy order."""
        if self.subprocess:
            for remote, data in zip(self.remotes, per_copy, strict=True):
                remote.send((cmd, data))
            return [remote.recv() for remote in self.remotes]
        if cmd == "step":
            return [c.step(a) for c, a in zip(self.copies, per_copy, strict=True)]
        return [c.reset(*data) for c, data in zip(self.copies, per_copy, strict=True)]

    def _call_copies(self, cmd: str, data: Any, indices: VecEnvIndices) -> list[Any]:
        """Run an attribute command on the copies of ``indices`` (slots); one result per slot."""
        slots = list(self._get_indices(indices))
        copies = sorted({s // self.n_robots for s in slots})
        results = {}
        if self.subprocess:
            for c in copies:
                self.remotes[c].send((cmd, data))
            results = {c: self.remotes[c].recv() for c in copies}
        else:
            for c in copies:
                env = self.copies[c].env
                if cmd == "get_attr":
                    results[c] = getattr(env, data)
                elif cmd == "set_attr":
                    results[c] = setattr(env, data[0], data[1])
                elif cmd == "env_method":
                    results[c] = getattr(env, data[0])(*data[1], **data[2])
                else:  # render
                    results[c] = env.render()
        return [results[s // self.n_robots] for s in slots]

    # ------------------------------------------------------------------ VecEnv API
    def seed(self, seed: int | None = None) -> list[int | None]:
        """Copy ``c`` gets ``seed + c`` at the next reset (a random base seed if None);
        returns the seed of every slot."""
        if seed is None:
            seed = int(np.random.default_rng().integers(np.iinfo(np.uint32).max))
        self._copy_seeds = [int(seed) + c for c in range(self.n_copies)]
        return [s for s in self._copy_seeds for _ in range(self.n_robots)]

    def reset(self) -> np.ndarray:
        # set_options() stores one dict per slot: a copy takes its first robot's.
        options = [self._options[c * self.n_robots] for c in range(self.n_copies)]
        results = self._call_all("reset", list(zip(self._copy_seeds, options, strict=True)))
        self._copy_seeds = [None] * self.n_copies
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [info for _, infos in results for info in infos]
        return np.concatenate([obs for obs, _ in results])

    def step_async(self, actions: np.ndarray) -> None:
        actions = np.asarray(actions)
        if actions.shape[0] != self.num_envs:
            raise ValueError(f"expected actions for {self.num_envs} slots, got {actions.shape}")
        self._actions = self._split(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        results = self._call_all("step", list(self._actions))
        self._actions = None
        if len(results) == 1:  # one copy: its arrays are the slots' (fresh at every step)
            obs, rewards, dones, infos, self.reset_infos = results[0]
            return obs, rewards, dones, infos
        obs, rewards, dones, infos, reset_infos = zip(*results, strict=True)
        self.reset_infos = [info for per_copy in reset_infos for info in per_copy]
        infos = [info for per_copy in infos for info in per_copy]
        return np.concatenate(obs), np.concatenate(rewards), np.concatenate(dones), infos

    def close(self) -> None:
        if self.closed:
            return
        if self.subprocess:
            for remote in self.remotes:
                remote.send(("close", None))
            for process in self.processes:
                process.join()
        else:
            for c in self.copies:
                c.env.close()
        self.closed = True

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._call_copies("get_attr", attr_name, indices)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._call_copies("set_attr", (attr_name, value), indices)

    def env_method(
        self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs
    ) -> list[Any]:
        return self._call_copies("env_method", (method_name, method_args, method_kwargs), indices)

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]  # copies are bare parallel envs

    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per copy (not per slot): the copy's robots share one scene."""
        return self._call_copies("render", None, list(range(0, self.num_envs, self.n_robots)))


def make_vec_env(
    n_copies: int = 1,
    seed: int | None = None,
    subprocess: bool = False,
    start_method: str | None = None,
    **env_kwargs: Any,
) -> SharedPolicyVecEnv:
    """``SharedPolicyVecEnv`` of ``astrobee_cargo_v0.parallel_env(**env_kwargs)``, seeded."""
    venv = SharedPolicyVecEnv(cargo_env_fn(**env_kwargs), n_copies, subprocess, start_method)
    if seed is not None:
        venv.seed(seed)
    return venv


def fast_inference(model: Any) -> Any:
    """Cut SB3's per-call overhead of ``model.predict`` without changing its actions:

    - ``policy.set_training_mode(mode)`` (which ``predict`` calls every time, and which walks
      every submodule through ``nn.Module.train``) returns at once when the policy is already
      in that mode;
    - torch's argument validation of distributions (``Normal``'s loc/scale checks at every
      construction) is switched off process-wide
      (``torch.distributions.Distribution.set_default_validate_args(False)``): it checks
      arguments only, the samples and log-probabilities are the same;
    - for an actor-critic policy with a diagonal Gaussian on a Box (PPO's and A2C's
      ``MlpPolicy`` without gSDE or squashing), ``policy.predict`` is ``_gaussian_predict``:
      the same mean, the same draw from torch's generator, without building the distribution
      object or SB3's observation checks (other policies keep SB3's ``predict``); when no
      module of the policy has forward hooks (checked here, once), the actor's layers run
      through their ``forward`` directly (``_plain_forward``), which skips torch's per-call
      hook dispatch and computes the same (SB3's ``FlattenExtractor`` as its two operations,
      float32 and flatten).

    Returns ``model``."""
    import torch
    from stable_baselines3.common.distributions import DiagGaussianDistribution
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.preprocessing import is_image_space

    torch.distributions.Distribution.set_default_validate_args(False)
    policy = model.policy
    set_mode = policy.set_training_mode

    def set_training_mode(mode: bool) -> None:
        if policy.training != mode:
            set_mode(mode)

    policy.set_training_mode = set_training_mode
    if (
        isinstance(policy, ActorCriticPolicy)
        and type(policy.action_dist) is DiagGaussianDistribution
        and not policy.squash_output
        and isinstance(policy.observation_space, spaces.Box)
        and isinstance(policy.action_space, spaces.Box)
        and not is_image_space(policy.observation_space)
    ):
        plain = not any(m._forward_hooks or m._forward_pre_hooks for m in policy.modules())
        policy.predict = functools.partial(_gaussian_predict, policy, policy.predict, plain)
    return model


def _plain_forward(module: Any, x: Any) -> Any:
    """``module(x)`` through ``forward`` (a ``Sequential`` layer by layer, as its own
    ``forward`` runs it): the same operations without torch's hook dispatch at every call."""
    import torch

    if isinstance(module, torch.nn.Sequential):
        for layer in module:
            x = _plain_forward(layer, x)
        return x
    return module.forward(x)


def _gaussian_predict(policy, sb3_predict, plain, observation, state=None, episode_start=None,
                      deterministic=False):  # fmt: skip
    """SB3's ``ActorCriticPolicy.predict`` for a diagonal Gaussian on a Box, step by step as SB3
    runs it: features of the observation (as float32), the actor's latent and mean action mu;
    deterministic: mu, else mu + eps sigma with eps ~ N(0, 1) drawn by ``Tensor.normal_`` of
    torch's generator (``Normal.rsample``) and sigma = exp(log_std); clipped to the action
    space (sigma broadcast over the batch: the same products as SB3's ones_like(mu) sigma).
    ``plain``: run the actor's layers with ``_plain_forward``. An observation that is not one or
    a batch of the space's shape goes to ``sb3_predict`` (which says what is wrong)."""
    import torch
    from stable_baselines3.common.policies import BaseModel
    from stable_baselines3.common.torch_layers import FlattenExtractor

    obs = np.asarray(observation)
    shape = policy.observation_space.shape
    vectorized = obs.shape[1:] == shape
    if obs.shape != shape and not vectorized:
        return sb3_predict(observation, state, episode_start, deterministic)
    policy.set_training_mode(False)
    with torch.no_grad():
        # The device of the policy's parameters (``policy.device`` walks them to find the first).
        obs_tensor = torch.as_tensor(obs.reshape((-1, *shape)), device=policy.log_std.device)
        if plain and type(policy.pi_features_extractor) is FlattenExtractor:
            # SB3's preprocessing of a non-image Box (float32) and its Flatten layer.
            features = obs_tensor.float().flatten(1)
        else:
            features = BaseModel.extract_features(policy, obs_tensor, policy.pi_features_extractor)
        if plain:
            latent = _plain_forward(policy.mlp_extractor.policy_net, features)
            mean = _plain_forward(policy.action_net, latent)
        else:
            mean = policy.action_net(policy.mlp_extractor.forward_actor(features))
        if deterministic:
            actions = mean
        else:
            std = policy.log_std.exp()
            actions = (
                mean + torch.empty(mean.shape, dtype=mean.dtype, device=mean.device).normal_() * std
            )
    space = policy.action_space
    actions = actions.cpu().numpy().reshape((-1, *space.shape))
    actions = np.clip(actions, space.low, space.high)
    return (actions if vectorized else actions.squeeze(axis=0)), state


# --------------------------------------------------------------------------- normalization


class CompiledRunningMeanStd(RunningMeanStd):
    """SB3's ``RunningMeanStd`` (state: ``mean``, ``var``, ``count``) whose ``update`` runs as one
    compiled kernel, ``_update_moments``, with numpy's arithmetic step for step: the same mean,
    var and count, bit for bit, as SB3's ``update`` on the same batches.

    ``update(x)`` with a batch x of n samples (rows): the batch moments as numpy computes them,
    m_B = x.mean(axis=0) and v_B = x.var(axis=0) in x's dtype, then SB3's
    ``update_from_moments`` (the parallel algorithm of Chan et al.) in float64:
    delta = m_B - mean, mean += delta n / (count + n),
    var = (var count + v_B n + delta^2 count n / (count + n)) / (count + n), count += n.
    The statistics are float64, as SB3 makes them. A batch that is not a C-contiguous float32
    or float64 array of rows of the statistics' shape (the layouts whose order of summation
    the kernel reproduces) goes through SB3's ``update``."""

    def update(self, arr: np.ndarray) -> None:
        shape = np.shape(self.mean)
        if not (
            isinstance(arr, np.ndarray)
            and arr.dtype in (np.float32, np.float64)
            and arr.ndim >= 1
            and arr.shape[0] > 0
            and arr.shape[1:] == shape
            and arr.flags.c_contiguous
        ):
            super().update(arr)
            return
        mean, var, count = _update_moments(
            arr.reshape(arr.shape[0], -1),
            np.asarray(self.mean, dtype=np.float64).reshape(-1),
            np.asarray(self.var, dtype=np.float64).reshape(-1),
            float(self.count),
        )
        # ``[()]``: a scalar for shape () (numpy's arithmetic on 0-d arrays gives one, so SB3's
        # return statistics are np.float64), the array itself otherwise.
        self.mean, self.var, self.count = mean.reshape(shape)[()], var.reshape(shape)[()], count

    def copy(self) -> CompiledRunningMeanStd:
        """A copy of the statistics, of this class (SB3's ``copy`` makes its own class)."""
        return compiled_statistics(super().copy())


def compiled_statistics(rms: RunningMeanStd) -> CompiledRunningMeanStd:
    """A ``CompiledRunningMeanStd`` holding a copy of ``rms``'s mean, var and count."""
    compiled = CompiledRunningMeanStd.__new__(CompiledRunningMeanStd)
    compiled.mean, compiled.var, compiled.count = rms.mean.copy(), rms.var.copy(), rms.count
    return compiled


def fast_normalization(venv: Any) -> Any:
    """Give a ``VecNormalize`` (or a ``VecEnv`` wrapping one) compiled running statistics:
    its observation statistics (each key's for a Dict space) and its return statistics become
    ``CompiledRunningMeanStd`` copies of themselves, which update to the same numbers as SB3's.
    Returns ``venv``."""
    from stable_baselines3.common.vec_env import VecNormalize, unwrap_vec_wrapper

    normalize = unwrap_vec_wrapper(venv, VecNormalize)
    if normalize is None:
        raise ValueError(f"no VecNormalize in {venv!r}")
    if isinstance(normalize.obs_rms, dict):
        normalize.obs_rms = {k: compiled_statistics(v) for k, v in normalize.obs_rms.items()}
    else:
        normalize.obs_rms = compiled_statistics(normalize.obs_rms)
    normalize.ret_rms = compiled_statistics(normalize.ret_rms)
    return venv


@njit(cache=True)
def _update_moments(x, mean, var, count):
    """SB3's ``update`` of the statistics (mean (d,), var (d,) float64, count) by the batch x
    (n, d) (float32 or float64, C-contiguous): the new mean, var and count.

    Batch moments as ``np.mean(x, axis=0)`` and ``np.var(x, axis=0)`` compute them: sums in x's
    dtype (``_column_sums``), each divided by n in float64 and rounded to x's dtype (numpy
    divides by the item count, an intp); v_B from the deviations e = x - m_B and their squares
    e * e, both in x's dtype. Then ``update_from_moments`` in float64, each operation in SB3's
    order; v_B n is numpy's product of x's dtype by a Python int: in x's dtype (rounded once
    from float64, where it is exact)."""
    n, d = x.shape
    sums = _column_sums(x)
    batch_mean = np.empty(d, x.dtype)
    for j in range(d):
        batch_mean[j] = sums[j] / n
    squares = np.empty_like(x)
    for i in range(n):
        for j in range(d):
            deviation = x[i, j] - batch_mean[j]
            squares[i, j] = deviation * deviation
    square_sums = _column_sums(squares)
    batch_var = np.empty(d, x.dtype)
    scaled_var = np.empty(d, x.dtype)
    for j in range(d):
        batch_var[j] = square_sums[j] / n
        scaled_var[j] = batch_var[j] * n
    total = count + n
    new_mean = np.empty(d)
    new_var = np.empty(d)
    for j in range(d):
        delta = batch_mean[j] - mean[j]
        new_mean[j] = mean[j] + delta * n / total
        m_2 = var[j] * count + scaled_var[j] + delta * delta * count * n / total
        new_var[j] = m_2 / total
    return new_mean, new_var, n + count


@njit(cache=True)
def _column_sums(x):
    """``x.sum(axis=0)`` of a C-contiguous (n, d) array as numpy sums it, in x's dtype: from
    numpy's initial 0, row after row (its loop runs along the rows' contiguous entries) when
    d > 1; the one contiguous column by numpy's pairwise sum (``_pairwise_sum``) when d = 1."""
    n, d = x.shape
    sums = np.zeros(d, x.dtype)
    if d == 1:
        sums[0] += _pairwise_sum(x[:, 0])
        return sums
    for i in range(n):
        for j in range(d):
            sums[j] += x[i, j]
    return sums


@njit(cache=True)
def _pairwise_sum(a):
    """numpy's pairwise summation of a 1-D run (``pairwise_sum``, numpy/_core/src/umath/
    loops_utils.h.src), in a's dtype: n < 8 one after the other from -0.0; n <= 128 in 8 interleaved
    accumulators (a_k, a_{k+8}, ... added to accumulator k), combined as
    ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), then the n mod 8 last entries one after
    the other; longer runs as the sum of the pairwise sums of their first n2 entries (n / 2
    rounded down to a multiple of 8) and of the rest."""
    n = a.size
    if n < 8:
        r = np.full(1, -0.0, a.dtype)
        for i in range(n):
            r[0] += a[i]
        return r[0]
    if n <= 128:
        r = a[:8].copy()
        i = 8
        while i < n - n % 8:
            for k in range(8):
                r[k] += a[i + k]
            i += 8
        total = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        for k in range(i, n):
            total += a[k]
        return total
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise_sum(a[:n2]) + _pairwise_sum(a[n2:])


class SlotController:
    """Drive every copy of a ``SharedPolicyVecEnv`` with a per-copy controller.

    ``controller.predict(obs (n_robots, obs_dim))`` returns ``(actions (n_robots, 8), state)``
    (``ObservationController`` does); ``predict`` here takes all slots (n_copies * n_robots,
    obs_dim), with SB3's signature, so it can be scored like a policy.
    """

    def __init__(self, controller: Any, n_robots: int) -> None:
        self.controller = controller
        self.n_robots = int(n_robots)

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        del episode_start, deterministic
        obs = np.asarray(observation)
        if obs.ndim != 2 or obs.shape[0] % self.n_robots:
            raise ValueError(
                f"observation must be (n_copies * {self.n_robots}, obs_dim), got {obs.shape}"
            )
        blocks = obs.reshape(-1, self.n_robots, obs.shape[1])
        actions = [self.controller.predict(block)[0] for block in blocks]
        return np.concatenate(actions).astype(np.float32), state


# --------------------------------------------------------------------------- single agent


class CentralizedCargoEnv(gymnasium.Env):
    """One policy drives all robots: observations and actions concatenated in agent order.

    Keyword arguments are those of ``astrobee_cargo_v0.parallel_env``. The reward is the mean of
    the robots' rewards (with the default ``shared_reward=1`` all robots get the team reward);
    ``info`` holds ``termination_reason`` and ``agents`` (each robot's info). The episode ends as
    the parallel env's does (its own truncation at ``max_cycles``: no ``TimeLimit`` is added).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 62}

    def __init__(self, render_mode: str | None = None, **env_kwargs: Any) -> None:
        self.parallel_env = make_cargo_env(render_mode=render_mode, **env_kwargs)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.parallel_env.metadata["render_fps"]}
        self.agents = list(self.parallel_env.possible_agents)
        obs_spaces = [self.parallel_env.observation_space(a) for a in self.agents]
        act_spaces = [self.parallel_env.action_space(a) for a in self.agents]
        self.obs_dim = obs_spaces[0].shape[0]
        self.act_dim = act_spaces[0].shape[0]
        self.observation_space = spaces.Box(
            np.concatenate([s.low for s in obs_spaces]),
            np.concatenate([s.high for s in obs_spaces]),
            dtype=np.float64,
        )
        self.action_space = spaces.Box(
            np.concatenate([s.low for s in act_spaces]),
            np.concatenate([s.high for s in act_spaces]),
            dtype=np.float32,
        )

    @property
    def sim(self) -> Any:
        """The parallel env's ``CargoTransport`` (truth, tracking error)."""
        return self.parallel_env.sim

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        obs, infos = self.parallel_env.reset(seed=seed, options=options)
        return self._concat(obs), {"agents": copy.deepcopy(infos)}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        per_robot = np.asarray(action, dtype=np.float64).reshape(len(self.agents), self.act_dim)
        obs, rewards, terms, truncs, infos = self.parallel_env.step(
            dict(zip(self.agents, per_robot, strict=True))
        )
        reward = float(np.mean([rewards[a] for a in self.agents]))
        terminated = any(terms[a] for a in self.agents)
        truncated = any(truncs[a] for a in self.agents) and not terminated
        info = {
            "termination_reason": infos[self.agents[0]].get("termination_reason"),
            # The parallel env may hand out one array in several steps' infos: copy.
            "agents": copy.deepcopy(infos),
        }
        return self._concat(obs), reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:
        return self.parallel_env.render()

    def close(self) -> None:
        self.parallel_env.close()

    def _concat(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([obs[a] for a in self.agents])
