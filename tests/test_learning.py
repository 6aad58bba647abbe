"""Learning wiring: the SB3 VecEnv adapter (slots, truncation against termination, seeding,
subprocesses), the single-agent Gymnasium view (both checkers, registration), tiny trainings
through both views (saving and loading give the same actions), and evaluate.py.

Tiny budgets, 20-step episodes, ideal noise and the estimators off wherever the test allows.
"""

import importlib.util
import json
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from pettingzoo import ParallelEnv
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from astrocargo.agents.controllers import ObservationController
from astrocargo.envs import astrobee_cargo_v0
from astrocargo.envs.wrappers import (
    ENV_ID,
    CentralizedCargoEnv,
    SharedPolicyVecEnv,
    SlotController,
    make_vec_env,
)

ROOT = Path(__file__).resolve().parents[1]
FAST = {
    "n_robots": 2,
    "noise": "ideal",
    "max_cycles": 20,
    "observe_estimates": False,
    "estimators": False,
}


def _load_script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rollout(venv, steps, seed=0):
    """Observations, rewards, dones of ``steps`` seeded random steps (from reset)."""
    rng = np.random.default_rng(seed)
    out = [venv.reset()]
    for _ in range(steps):
        obs, rewards, dones, _ = venv.step(rng.uniform(-1, 1, (venv.num_envs, 8)))
        out += [obs, rewards, dones]
    return out


# --------------------------------------------------------------------------- VecEnv adapter


def test_slots_follow_copies_and_agents():
    venv = make_vec_env(2, seed=5, **FAST)
    obs = venv.reset()
    assert venv.num_envs == 4 and obs.shape == (4, venv.observation_space.shape[0])
    env = astrobee_cargo_v0.parallel_env(**FAST)
    direct, _ = env.reset(seed=6)  # copy 1 is seeded 5 + 1
    np.testing.assert_array_equal(obs[2], direct["astrobee_0"])
    np.testing.assert_array_equal(obs[3], direct["astrobee_1"])
    venv.close()


def test_truncation_is_reported_for_bootstrapping():
    venv = make_vec_env(1, seed=0, **FAST)
    env = astrobee_cargo_v0.parallel_env(**FAST)
    venv.reset()
    env.reset(seed=0)
    zeros = np.zeros((2, 8))
    for k in range(FAST["max_cycles"]):
        obs, rewards, dones, infos = venv.step(zeros)
        direct = env.step({a: np.zeros(8) for a in env.agents})
        assert dones.tolist() == [k == FAST["max_cycles"] - 1] * 2
    for i, agent in enumerate(env.possible_agents):
        assert infos[i]["TimeLimit.truncated"] is True
        np.testing.assert_array_equal(infos[i]["terminal_observation"], direct[0][agent])
        assert rewards[i] == pytest.approx(direct[1][agent])
    # The copy has reset itself: the returned observation starts the next episode.
    assert not np.array_equal(obs[0], infos[0]["terminal_observation"])
    venv.close()


class _EndsAtThree(ParallelEnv):
    """Two agents; every episode ends at step 3 by termination (truncated too if asked)."""

    metadata = {"name": "ends_at_three_v0"}

    def __init__(self, truncate_too=False):
        self.possible_agents = ["a", "b"]
        self.truncate_too = truncate_too
        self._obs = spaces.Box(-10, 10, (2,), np.float64)
        self._act = spaces.Box(-1, 1, (8,), np.float32)
        self.render_mode = None

    def observation_space(self, agent):
        return self._obs

    def action_space(self, agent):
        return self._act

    def reset(self, seed=None, options=None):
        self.agents, self.t = self.possible_agents[:], 0
        return {a: np.zeros(2) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self.t += 1
        end = self.t == 3
        obs = {a: np.full(2, float(self.t)) for a in self.agents}
        if end:
            self.agents = []
        agents = self.possible_agents
        return (
            obs,
            dict.fromkeys(agents, 1.0),
            dict.fromkeys(agents, end),
            dict.fromkeys(agents, end and self.truncate_too),
            {a: {} for a in agents},
        )


@pytest.mark.parametrize("truncate_too", [False, True])
def test_termination_is_not_truncation(truncate_too):
    venv = SharedPolicyVecEnv(lambda: _EndsAtThree(truncate_too), n_copies=2)
    venv.reset()
    for _ in range(3):
        obs, _, dones, infos = venv.step(np.zeros((4, 8)))
    assert dones.all()
    assert [info["TimeLimit.truncated"] for info in infos] == [False] * 4
    np.testing.assert_array_equal(infos[0]["terminal_observation"], [3.0, 3.0])
    np.testing.assert_array_equal(obs, np.zeros((4, 2)))


def test_seeding_is_per_copy_and_reproducible_in_subprocesses():
    kwargs = {**FAST, "noise": "nominal", "max_cycles": 6}
    a = _rollout(make_vec_env(2, seed=11, **kwargs), 8)  # crosses an auto-reset
    b = _rollout(make_vec_env(2, seed=11, **kwargs), 8)
    # "fork": the default forkserver takes seconds to start on a loaded 2-core machine.
    venv = make_vec_env(2, seed=11, subprocess=True, start_method="fork", **kwargs)
    c = _rollout(venv, 8)
    assert venv.get_attr("max_cycles") == [6] * 4
    venv.close()
    for x, y, z in zip(a, b, c, strict=True):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)
    assert not np.array_equal(a[0][:2], a[0][2:])  # the copies differ
    d = _rollout(make_vec_env(2, seed=12, **kwargs), 0)
    assert not np.array_equal(a[0], d[0])


def test_slot_controller_drives_the_adapter_like_the_env():
    kwargs = {**FAST, "observe_estimates": True, "estimators": True}
    venv = make_vec_env(1, seed=3, **kwargs)
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    obs_dict, _ = env.reset(seed=3)
    controller = ObservationController.for_env(env, "estimate")
    slots = SlotController(controller, n_robots=2)
    obs = venv.reset()
    for _ in range(10):
        actions, _ = slots.predict(obs)
        obs, _, _, _ = venv.step(actions)
        direct, _ = controller.predict(obs_dict)
        obs_dict, *_ = env.step(direct)
        np.testing.assert_allclose(obs, np.stack(list(obs_dict.values())), atol=1e-6)
    venv.close()


# --------------------------------------------------------------------------- single agent


def test_centralized_view_passes_both_checkers():
    env = CentralizedCargoEnv(**FAST)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded Box observations: both warn, neither fails
        gymnasium_check_env(env, skip_render_check=True)
        sb3_check_env(env)
    assert env.observation_space.shape == (2 * env.obs_dim,)
    assert env.action_space.shape == (16,)
    made = gymnasium.make(f"astrocargo.envs.wrappers:{ENV_ID}", **FAST)
    obs, _ = made.reset(seed=2)
    for _ in range(FAST["max_cycles"]):
        obs, reward, terminated, truncated, info = made.step(made.action_space.sample() * 0)
    assert truncated and not terminated and info["termination_reason"] is None
    made.close()


# --------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def trained_runs(tmp_path_factory):
    """One PPO run through the adapter and one SAC run through the single-agent view."""
    train = _load_script("train")
    base = tmp_path_factory.mktemp("runs")
    common = ["--max-cycles", "20", "--noise", "ideal", "--no-progress-bar", "--seed", "4"]
    ppo = train.main(
        ["--algo", "ppo", "--copies", "2", "--timesteps", "256", "--log-dir", str(base / "ppo")]
        + common
        + ["--hyperparams", "n_steps=32", "batch_size=64", "n_epochs=1"]
    )
    sac = train.main(
        ["--algo", "sac", "--view", "central", "--copies", "1", "--timesteps", "64"]
        + ["--no-estimates", "--log-dir", str(base / "sac")]
        + common
        + ["--hyperparams", "learning_starts=32", "batch_size=16", "buffer_size=1000"]
    )
    assert ppo == sac == 0
    return base


@pytest.mark.parametrize("run", ["ppo", "sac"])
def test_training_saves_and_loads_same_actions(trained_runs, run):
    evaluate = _load_script("evaluate")
    run_dir = trained_runs / run
    config = json.loads((run_dir / "config.json").read_text())
    assert config["seed"] == 4 and config["samples"] >= config["timesteps"]
    assert (run_dir / "monitor.csv").is_file() and any((run_dir / "tb").iterdir())
    policy = evaluate.TrainedPolicy(run_dir)
    env = astrobee_cargo_v0.parallel_env(**config["env_kwargs"])
    obs, _ = env.reset(seed=0)
    obs = np.stack(list(obs.values()))
    # The same policy object again from disk, and its normalised, deterministic actions.
    again = evaluate.TrainedPolicy(run_dir)
    np.testing.assert_array_equal(policy.act(obs), again.act(obs))
    flat = obs.reshape(1, -1) if config["view"] == "central" else obs
    direct, _ = again.model.predict(again.normalizer.normalize_obs(flat), deterministic=True)
    np.testing.assert_array_equal(policy.act(obs), direct.reshape(2, 8))


def test_training_run_saves_the_in_memory_policy(tmp_path):
    train = _load_script("train")
    args = train.build_parser().parse_args(
        ["--copies", "1", "--timesteps", "64", "--max-cycles", "20", "--noise", "ideal"]
        + ["--no-progress-bar", "--log-dir", str(tmp_path), "--no-estimates"]
        + ["--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"]
    )
    model, run_dir = train.train(args)
    evaluate = _load_script("evaluate")
    loaded = evaluate.TrainedPolicy(run_dir)
    obs = np.random.default_rng(0).normal(size=(2, model.observation_space.shape[0]))
    expected, _ = model.predict(loaded.normalizer.normalize_obs(obs), deterministic=True)
    np.testing.assert_array_equal(loaded.act(obs), expected)


def test_evaluate_scores_policies_on_the_same_episodes(trained_runs, tmp_path):
    evaluate = _load_script("evaluate")
    out = tmp_path / "eval.json"
    argv = ["--policy", str(trained_runs / "ppo"), "zero", "scripted", "--episodes", "2"]
    assert evaluate.main(argv + ["--json", str(out)]) == 0
    results = json.loads(out.read_text())
    assert results["task"]["max_cycles"] == 20
    names = [r["policy"] for r in results["results"]]
    assert names == [str(trained_runs / "ppo"), "zero", "scripted (estimate)"]
    for r in results["results"]:
        assert [e["seed"] for e in r["episodes"]] == [1000, 1001]
        assert set(r["summary"]) >= {"return", "track_pos_m", "mass_rel_err"}
    zero, scripted = results["results"][1:]
    # The scripted controller follows the reference that the zero policy lets go.
    assert scripted["summary"]["final_pos_m"]["mean"] < zero["summary"]["final_pos_m"]["mean"]
