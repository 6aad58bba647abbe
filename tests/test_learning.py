"""Learning wiring: the SB3 VecEnv adapter (slots, truncation against termination, seeding,
subprocesses), the single-agent Gymnasium view (both checkers, registration), tiny trainings
through both views (saving and loading give the same actions), and evaluate.py.

Tiny budgets, 20-step episodes, ideal noise and the estimators off wherever the test allows.
"""

import json
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from learning_setup import FAST, load_script, rollout
from pettingzoo import ParallelEnv
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from astrocargo.agents.controllers import ObservationController
from astrocargo.agents.feedforward import FeedForwardObservation
from astrocargo.envs import astrobee_cargo_v0
from astrocargo.envs.config import LEARNING_TASKS
from astrocargo.envs.decision import DecisionEnv, cargo_env_fn
from astrocargo.envs.wrappers import (
    ENV_ID,
    CentralizedCargoEnv,
    SharedPolicyVecEnv,
    SlotController,
    fast_inference,
    make_vec_env,
)
from astrocargo.estimator.inertia import mass_com_inertia_from_params
from astrocargo.estimator.prior import default_prior

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
    a = rollout(make_vec_env(2, seed=11, **kwargs), 8)  # crosses an auto-reset
    b = rollout(make_vec_env(2, seed=11, **kwargs), 8)
    # "fork": the default forkserver takes seconds to start on a loaded 2-core machine.
    venv = make_vec_env(2, seed=11, subprocess=True, start_method="fork", **kwargs)
    c = rollout(venv, 8)
    assert venv.get_attr("max_cycles") == [6] * 4
    venv.close()
    for x, y, z in zip(a, b, c, strict=True):
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(x, z)
    assert not np.array_equal(a[0][:2], a[0][2:])  # the copies differ
    d = rollout(make_vec_env(2, seed=12, **kwargs), 0)
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
    train = load_script("train")
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
    res = train.main(
        ["--algo", "ppo", "--copies", "1", "--timesteps", "64", "--log-dir", str(base / "res")]
        + ["--residual-scale", "0.3", "--action-repeat", "2", "--no-estimates"]
        + ["--checkpoint-every", "32"]
        + common
        + ["--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"]
    )
    resb = train.main(
        ["--algo", "ppo", "--copies", "1", "--timesteps", "64", "--log-dir", str(base / "resb")]
        + ["--residual-scale", "0.3", "--action-repeat", "2", "--base-model", "estimate"]
        + ["--no-estimates"]
        + common
        + ["--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"]
    )
    resff = train.main(
        ["--algo", "ppo", "--copies", "1", "--timesteps", "64", "--log-dir", str(base / "resff")]
        + ["--residual-scale", "1.0", "--action-repeat", "2", "--feedforward-obs"]
        + common
        + ["--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"]
    )
    assert ppo == sac == res == resb == resff == 0
    return base


@pytest.mark.parametrize("run", ["ppo", "sac", "res", "resb"])
def test_training_saves_and_loads_same_actions(trained_runs, run):
    evaluate = load_script("evaluate")
    run_dir = trained_runs / run
    config = json.loads((run_dir / "config.json").read_text())
    assert config["seed"] == 4 and config["samples"] >= config["timesteps"]
    assert (run_dir / "monitor.csv").is_file() and any((run_dir / "tb").iterdir())
    policy = evaluate.TrainedPolicy(run_dir)
    env = cargo_env_fn(**config["env_kwargs"])()
    obs, _ = env.reset(seed=0)
    obs = np.stack(list(obs.values()))
    if config["env_kwargs"].get("hide_estimates"):
        policy.policy_obs = slice(None)  # the policy's view (env.reset gave it), as-is
    # The same policy object again from disk, and its normalised, deterministic actions.
    again = evaluate.TrainedPolicy(run_dir)
    np.testing.assert_array_equal(policy.decide(obs), again.decide(obs))
    flat = obs.reshape(1, -1) if config["view"] == "central" else obs
    direct, _ = again.model.predict(again.normalizer.normalize_obs(flat), deterministic=True)
    np.testing.assert_array_equal(policy.decide(obs), direct.reshape(2, -1))


def test_training_run_saves_the_in_memory_policy(tmp_path):
    train = load_script("train")
    args = train.build_parser().parse_args(
        ["--copies", "1", "--timesteps", "64", "--max-cycles", "20", "--noise", "ideal"]
        + ["--no-progress-bar", "--log-dir", str(tmp_path), "--no-estimates"]
        + ["--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"]
    )
    model, run_dir = train.train(args)
    evaluate = load_script("evaluate")
    loaded = evaluate.TrainedPolicy(run_dir)
    obs = np.random.default_rng(0).normal(size=(2, model.observation_space.shape[0]))
    expected, _ = model.predict(loaded.normalizer.normalize_obs(obs), deterministic=True)
    np.testing.assert_array_equal(loaded.act(obs), expected)


def test_evaluate_scores_policies_on_the_same_episodes(trained_runs, tmp_path):
    evaluate = load_script("evaluate")
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
    # Earlier results join the table when scored on the same episodes, and only then.
    again = tmp_path / "again.json"
    argv = ["--policy", "zero", "--episodes", "2", "--results", str(out), "--json", str(again)]
    assert evaluate.main(argv) == 0
    joined = json.loads(again.read_text())["results"]
    assert [r["policy"] for r in joined] == ["zero", *names]
    assert joined[0]["episodes"] == joined[2]["episodes"]  # the zero policy, scored again
    with pytest.raises(ValueError, match="other episodes"):
        evaluate.main(["--results", str(out), "--episodes", "3"])


# --------------------------------------------------------------------------- tasks, decisions


def test_cargo_task_draws_masses_over_its_range_with_matching_inertia():
    task = {**LEARNING_TASKS["cargo"], "max_cycles": 5, "noise": "ideal", "estimators": False}
    task["observe_estimates"] = False
    env = cargo_env_fn(**task)()
    masses = []
    for seed in range(12):
        env.reset(seed=seed)
        world = env.sim.world
        mass, com, inertia = mass_com_inertia_from_params(world.cargo_params())
        masses.append(mass)
        # The inertia about the centre of mass is the uniform box's of the drawn mass.
        np.testing.assert_allclose(inertia, world.uniform_cargo_inertia(mass), atol=1e-12)
        assert np.all(np.abs(com) <= 0.03 + 1e-12)
    low, high = LEARNING_TASKS["cargo"]["cargo_mass_kg"]
    assert low <= min(masses) and max(masses) <= high
    assert max(masses) - min(masses) > 0.5 * (high - low)
    env.close()


def test_zero_residual_is_the_scripted_no_model_controller():
    kwargs = {**FAST, "max_cycles": 12}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    wrapped = DecisionEnv(astrobee_cargo_v0.parallel_env(**kwargs), residual_scale=0.4)
    obs, _ = env.reset(seed=7)
    wobs, _ = wrapped.reset(seed=7)
    controller = ObservationController.for_env(env, "none")
    zeros = dict.fromkeys(env.possible_agents, np.zeros(6))
    assert wrapped.action_space("astrobee_0").shape == (6,)  # thrust only
    while env.agents:
        obs, rewards, *_ = env.step(controller.predict(obs)[0])
        wobs, wrewards, _, _, winfos = wrapped.step(zeros)
        for a in env.possible_agents:
            np.testing.assert_array_equal(obs[a], wobs[a])
            assert rewards[a] == wrewards[a]
    assert not wrapped.agents and winfos["astrobee_0"]["decision_steps"] == 1


def test_zero_residual_on_the_estimate_base_is_the_live_estimate_controller():
    kwargs = {**FAST, "max_cycles": 12, "observe_estimates": True, "estimators": True}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    wrapped = cargo_env_fn(residual_scale=0.4, base_model="estimate", **kwargs)()
    obs, _ = env.reset(seed=7)
    wrapped.reset(seed=7)
    controller = ObservationController.for_env(env, "estimate")
    none = ObservationController.for_env(env, "none")
    zeros = dict.fromkeys(env.possible_agents, np.zeros(6))
    differs = False
    while env.agents:
        actions = controller.predict(obs)[0]
        differs |= any(np.any(actions[a] != none.predict(obs)[0][a]) for a in env.agents)
        obs, rewards, *_ = env.step(actions)
        wobs, wrewards, *_ = wrapped.step(zeros)
        for a in env.possible_agents:
            np.testing.assert_array_equal(obs[a], wobs[a])
            assert rewards[a] == wrewards[a]
    assert differs  # the estimate changes the base's action: the test can tell the two apart


def test_hidden_estimates_leave_the_policy_without_them_and_the_base_with_them():
    kwargs = {**FAST, "max_cycles": 12, "observe_estimates": True, "estimators": True}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    seen = cargo_env_fn(residual_scale=0.4, base_model="estimate", **kwargs)()
    hidden = cargo_env_fn(
        residual_scale=0.4, base_model="estimate", hide_estimates=True, **kwargs
    )()
    layout = env.sim.obs_layout
    keep = np.ones(layout["all"].stop, dtype=bool)
    keep[layout["estimate_mean"]] = keep[layout["estimate_std"]] = False
    obs, _ = env.reset(seed=3)
    sobs, _ = seen.reset(seed=3)
    hobs, _ = hidden.reset(seed=3)
    assert hidden.observation_space("astrobee_0").shape == (int(keep.sum()),)
    assert seen.observation_space("astrobee_0").shape == (layout["all"].stop,)
    residual = dict.fromkeys(env.possible_agents, np.full(6, 0.5))
    while hidden.agents:
        for a in env.possible_agents:
            np.testing.assert_array_equal(hobs[a], sobs[a][keep])
            assert hidden.observation_space(a).contains(hobs[a].astype(np.float32))
        sobs, *_ = seen.step(residual)
        hobs, *_ = hidden.step(residual)  # the same physics: the base still reads the estimates


def _at_reference(obs: dict[str, np.ndarray], layout: dict[str, slice]) -> dict:
    """The observations with zero tracking errors, the base turning at the reference's rate
    and every arm at rest: the scripted controller's feedback is then zero."""
    out = {}
    for a, o in obs.items():
        o = o.copy()
        for name in ("base_pos_err", "base_vel_err", "base_att_err"):
            o[layout[name]] = 0.0
        o[layout["base_ang_vel"]] = o[layout["ref_ang_vel"]]
        for name in [n for n in layout if n.endswith("joint_vel")]:
            o[layout[name]] = 0.0
        out[a] = o
    return out


def test_feedforward_input_is_the_scripted_feedforward_of_the_estimate():
    kwargs = {**FAST, "max_cycles": 60, "observe_estimates": True, "estimators": True}
    env = astrobee_cargo_v0.parallel_env(**kwargs, cargo_mass_kg=12.0)
    obs, _ = env.reset(seed=5)
    layout = env.sim.obs_layout
    estimate, none = (ObservationController.for_env(env, m) for m in ("estimate", "none"))
    for _ in range(40):  # the reference accelerates from rest
        obs, *_ = env.step(estimate.predict(obs)[0])
    feedforward = FeedForwardObservation(env, "estimate")
    at_ref = _at_reference(obs, layout)
    u_ff = feedforward(at_ref)
    scripted = {a: estimate.predict(at_ref)[0][a][:6] - none.predict(at_ref)[0][a][:6] for a in obs}
    for a in obs:
        assert u_ff[a].shape == (6,)
        assert np.max(np.abs(u_ff[a])) > 1e-3  # the cargo's feed-forward is not nothing
        np.testing.assert_allclose(u_ff[a], scripted[a], rtol=1e-10, atol=1e-12)
    # With tracking errors the correction holds the feedback too; the input does not.
    moved = {a: o.copy() for a, o in at_ref.items()}
    for o in moved.values():
        o[layout["base_vel_err"]] = 0.05
    diff = {a: estimate.predict(moved)[0][a][:6] - none.predict(moved)[0][a][:6] for a in obs}
    for a in obs:
        np.testing.assert_allclose(feedforward(moved)[a], u_ff[a], rtol=1e-10, atol=1e-12)
        assert np.max(np.abs(diff[a] - u_ff[a])) > 1e-3
    # The prior's input is the estimate's when the estimate is the prior.
    prior = FeedForwardObservation(env, "prior")
    for a, robot in zip(env.possible_agents, env.sim.robots, strict=True):
        at_ref[a][layout["estimate_mean"]] = default_prior(robot)
    np.testing.assert_allclose(
        np.stack(list(prior(at_ref).values())), np.stack(list(feedforward(at_ref).values()))
    )
    env.close()


@pytest.mark.parametrize("observe", [True, False])
def test_decision_env_appends_the_feedforward_input(observe):
    kwargs = {**FAST, "max_cycles": 12, "observe_estimates": observe, "estimators": observe}
    source = "estimate" if observe else "prior"
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    wrapped = cargo_env_fn(residual_scale=1.0, feedforward_obs=source, **kwargs)()
    dim = env.sim.obs_layout["all"].stop
    assert wrapped.observation_space("astrobee_0").shape == (dim + 6,)
    obs, _ = env.reset(seed=7)
    wobs, _ = wrapped.reset(seed=7)
    controller = ObservationController.for_env(env, "none")
    feedforward = FeedForwardObservation(env, source)
    zeros = dict.fromkeys(env.possible_agents, np.zeros(6))
    while True:
        u_ff = feedforward(obs)
        for a in env.possible_agents:
            np.testing.assert_array_equal(wobs[a][:dim], obs[a])
            np.testing.assert_array_equal(wobs[a][dim:], u_ff[a])
            assert wrapped.observation_space(a).contains(wobs[a].astype(np.float32))
        if not env.agents:
            break
        obs, *_ = env.step(controller.predict(obs)[0])
        wobs, *_ = wrapped.step(zeros)
    with pytest.raises(ValueError):  # the live estimate needs the estimates observed
        cargo_env_fn(residual_scale=1.0, feedforward_obs="estimate", **FAST)()


@pytest.mark.parametrize(
    "kwargs",
    [{"base_model": "truth"}, {"hide_estimates": True}],
)
def test_decision_env_rejects_bad_bases_and_hiding_what_is_not_observed(kwargs):
    with pytest.raises(ValueError):
        cargo_env_fn(residual_scale=0.3, **kwargs, **FAST)()


def test_action_repeat_holds_the_action_and_sums_the_rewards():
    kwargs = {**FAST, "max_cycles": 7}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    wrapped = DecisionEnv(astrobee_cargo_v0.parallel_env(**kwargs), action_repeat=3)
    env.reset(seed=2)
    wrapped.reset(seed=2)
    action = dict.fromkeys(env.possible_agents, np.array([0.5, -0.3, 0.2, 0.1, 0, 0, 0, 0.2]))
    steps = []
    while wrapped.agents:
        wobs, wrewards, _, truncs, infos = wrapped.step(action)
        total = dict.fromkeys(env.possible_agents, 0.0)
        for _ in range(infos["astrobee_0"]["decision_steps"]):
            obs, rewards, *_ = env.step(action)
            for a in rewards:
                total[a] += rewards[a]
        steps.append(infos["astrobee_0"]["decision_steps"])
        for a in env.possible_agents:
            np.testing.assert_array_equal(obs[a], wobs[a])
            assert wrewards[a] == pytest.approx(total[a], rel=1e-12)
    assert steps == [3, 3, 1] and all(truncs.values())  # the episode ends within a decision


@pytest.mark.parametrize(
    "kwargs", [{"residual_scale": -0.1}, {"action_repeat": 0}, {"action_repeat": 1.5}]
)
def test_decision_env_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        DecisionEnv(astrobee_cargo_v0.parallel_env(**FAST), **kwargs)


@pytest.mark.parametrize("run", ["res", "resb", "resff"])
def test_evaluation_replays_a_residual_policy_as_in_training(trained_runs, run):
    """evaluate.py's TrainedPolicy at the control rate (repeat, residual on its base, the
    hidden estimates and the feed-forward input done by itself) and the training env's
    DecisionEnv driven by the same model make the same episode."""
    evaluate = load_script("evaluate")
    policy = evaluate.TrainedPolicy(trained_runs / run)
    kwargs = policy.config["env_kwargs"]
    assert kwargs["residual_scale"] == (1.0 if run == "resff" else 0.3)
    assert kwargs["action_repeat"] == 2
    assert kwargs.get("hide_estimates", False) == (run == "resb")
    assert kwargs.get("feedforward_obs") == ("estimate" if run == "resff" else None)
    wrapped = cargo_env_fn(**kwargs)()
    decision = ("residual_scale", "action_repeat", "base_model", "hide_estimates")
    decision += ("feedforward_obs",)
    bare = astrobee_cargo_v0.parallel_env(**{k: v for k, v in kwargs.items() if k not in decision})
    wobs, _ = wrapped.reset(seed=3)
    obs, _ = bare.reset(seed=3)
    policy.reset(bare)
    agents = bare.possible_agents
    moved = False
    view = policy.policy_obs
    feedforward = policy.feedforward
    while wrapped.agents:
        # The wrapped env hands the policy its view (estimates hidden, feed-forward appended).
        policy.policy_obs, policy.feedforward = slice(None), None
        decision = policy.decide(np.stack([wobs[a] for a in agents]))
        policy.policy_obs, policy.feedforward = view, feedforward
        moved |= bool(np.any(decision))
        wobs, *_ = wrapped.step(dict(zip(agents, decision, strict=True)))
        for _ in range(2):
            if bare.agents:
                obs, *_ = bare.step(
                    dict(zip(agents, policy.act(np.stack([obs[a] for a in agents])), strict=True))
                )
        for a in agents:
            np.testing.assert_array_equal(obs[a][view], wobs[a][: len(obs[a][view])])
    assert moved  # the residual is not zero: the comparison tests the residual path


def test_a_checkpoint_is_a_policy_of_its_own_arm(trained_runs):
    evaluate = load_script("evaluate")
    report = load_script("eval_report")
    run = trained_runs / "res"
    assert evaluate.checkpoint_samples(run) == [32, 64]
    final, early = (evaluate.make_policy(spec, "estimate") for spec in (str(run), f"{run}@32"))
    assert early.name == f"{run}@32" and early.config["checkpoint_samples"] == 32
    assert report.arm_key(early.config) == report.arm_key(final.config).replace(
        "(64 samples)", "(checkpoint at 32 samples)"
    )
    with pytest.raises(ValueError, match="no checkpoint"):
        evaluate.check_policy_spec(f"{run}@48")


def test_fast_inference_keeps_the_actions(trained_runs):
    from stable_baselines3 import PPO

    run = trained_runs / "ppo"
    obs = np.random.default_rng(1).normal(
        size=(4, PPO.load(run / "model.zip").observation_space.shape[0])
    )
    plain, fast = PPO.load(run / "model.zip"), fast_inference(PPO.load(run / "model.zip"))
    for deterministic in (True, False):
        for batch in (obs, obs[0]):  # a batch, and one observation (its actions unbatched)
            plain.set_random_seed(5)  # torch's global generator: seed right before each call
            a, _ = plain.predict(batch, deterministic=deterministic)
            fast.set_random_seed(5)
            b, _ = fast.predict(batch, deterministic=deterministic)
            assert a.shape == b.shape and a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    # A run of draws stays in step with SB3's.
    plain.set_random_seed(6)
    runs = [plain.predict(obs)[0] for _ in range(5)]
    fast.set_random_seed(6)
    np.testing.assert_array_equal(runs, [fast.predict(obs)[0] for _ in range(5)])
    with pytest.raises(ValueError, match="observation shape"):  # SB3's check still answers
        fast.predict(obs[:, :3])
    fast.policy.set_training_mode(True)  # a change of mode still reaches every submodule
    assert all(m.training for m in fast.policy.modules())
    fast.policy.set_training_mode(False)
    assert not any(m.training for m in fast.policy.modules())


def test_ablation_compares_arms_with_the_seed_spread():
    report = load_script("eval_report")

    def result(observe, seed, light, heavy):
        config = {
            "algo": "ppo",
            "view": "shared",
            "task": "cargo",
            "seed": seed,
            "env_kwargs": {"observe_estimates": observe, "residual_scale": 0.3},
        }
        bins = {
            name: {m: {"mean": value, "std": 0.0} for m in report.ABLATION_METRICS}
            for name, value in (("light", light), ("heavy", heavy))
        }
        return {"config": config, "bins": bins}

    results = [result(True, s, 0.010 + 0.001 * s, 0.004 + 0.0001 * s) for s in (1, 2, 3)]
    results += [result(False, s, 0.011 + 0.001 * s, 0.020 + 0.0001 * s) for s in (1, 2, 3)]
    table = report.ablation(results)
    assert len(table["arms"]) == 2 and len(table["pairs"]) == 1
    arm = table["arms"][table["pairs"][0]["with"]]
    assert arm["seeds"] == [1, 2, 3]
    assert arm["bins"]["light"]["track_pos_m"]["std"] == pytest.approx(0.001)
    diffs = table["pairs"][0]["bins"]
    assert diffs["light"]["track_pos_m"]["with_minus_without"] == pytest.approx(-0.001)
    assert diffs["light"]["track_pos_m"]["exceeds_spread"] is False  # 1 mm, spread 1 mm
    assert diffs["heavy"]["track_pos_m"]["with_minus_without"] == pytest.approx(-0.016)
    assert diffs["heavy"]["track_pos_m"]["exceeds_spread"] is True


def test_ablation_pairs_hidden_estimates_on_the_estimate_base():
    report = load_script("eval_report")

    def result(base, hide, seed):
        kwargs = {"observe_estimates": True, "residual_scale": 0.3, "base_model": base}
        config = {"algo": "ppo", "view": "shared", "task": "cargo", "seed": seed}
        bins = {"all": {m: {"mean": 0.01 * seed, "std": 0.0} for m in report.ABLATION_METRICS}}
        return {
            "config": {**config, "env_kwargs": {**kwargs, "hide_estimates": hide}},
            "bins": bins,
        }

    results = [result("estimate", hide, s) for hide in (False, True) for s in (1, 2)]
    results += [result("none", False, s) for s in (1, 2)]
    table = report.ablation(results)
    assert len(table["arms"]) == 3 and len(table["pairs"]) == 1  # the none arm has no partner
    pair = table["pairs"][0]
    assert "on estimate" in pair["with"] and pair["with"].endswith("with estimates")
    assert "on estimate" in pair["without"] and pair["without"].endswith("without estimates")


def test_ablation_pairs_the_feedforward_arms_apart_from_the_plain_ones():
    report = load_script("eval_report")

    def result(observe, feedforward, seed):
        kwargs = {"observe_estimates": observe, "residual_scale": 1.0}
        if feedforward:
            kwargs["feedforward_obs"] = "estimate" if observe else "prior"
        config = {"algo": "ppo", "view": "shared", "task": "cargo", "seed": seed}
        bins = {"all": {m: {"mean": 0.01 * seed, "std": 0.0} for m in report.ABLATION_METRICS}}
        return {"config": {**config, "env_kwargs": kwargs}, "bins": bins}

    results = [result(o, f, s) for o in (True, False) for f in (True, False) for s in (1, 2)]
    table = report.ablation(results)
    assert len(table["arms"]) == 4 and len(table["pairs"]) == 2
    for pair in table["pairs"]:
        assert ("feed-forward" in pair["with"]) == ("feed-forward" in pair["without"])


def test_evaluate_bins_masses_and_bounds_the_principal_moments(tmp_path):
    evaluate = load_script("evaluate")
    out = tmp_path / "eval.json"
    argv = ["--policy", "scripted", "scripted:none@figure8_tumble", "--episodes", "1"]
    argv += ["--task", "cargo", "--max-cycles", "400", "--mass-bins", "1,5,20", "--bound"]
    assert evaluate.main(argv + ["--json", str(out)]) == 0
    results = json.loads(out.read_text())
    assert results["mass_bins"] == [[1.0, 5.0], [5.0, 20.0]]
    estimate, tumble = results["results"]
    assert tumble["policy"] == "scripted (none) on figure8_tumble"
    for r in (estimate, tumble):
        masses = [e["cargo_mass_kg"] for e in r["episodes"]]
        assert 1 <= masses[0] < 5 <= masses[1] <= 20
        assert [e["bin"] for e in r["episodes"]] == ["1-5 kg", "5-20 kg"]
        for e in r["episodes"]:
            assert len(e["bound_principal_rel"]) == 3 and e["steps"] == 400
            assert 0 <= e["saturated"] <= 1 and e["wall_contact"] == 0
    # Tumbling reveals the principal moments that the yaw ramp leaves to the prior.
    worst = [max(e["filter_principal_rel"]) for e in estimate["episodes"]]
    worst_tumble = [max(e["filter_principal_rel"]) for e in tumble["episodes"]]
    assert np.all(np.array(worst_tumble) < np.array(worst))


def test_correction_is_what_the_estimate_adds_and_grows_with_the_mass(tmp_path):
    evaluate = load_script("evaluate")
    out = tmp_path / "eval.json"
    argv = ["--policy", "scripted", "scripted:none", "feedforward", "--episodes", "1"]
    argv += ["--task", "cargo", "--max-cycles", "450", "--mass-bins", "1,2,19,20", "--correction"]
    assert evaluate.main(argv + ["--json", str(out)]) == 0
    estimate, none, feedforward = json.loads(out.read_text())["results"]
    # The no-model controller plus the feed-forward input as it is tracks a heavy cargo better.
    heaviest = "19-20 kg"
    assert (
        feedforward["bins"][heaviest]["track_pos_m"]["mean"]
        < none["bins"][heaviest]["track_pos_m"]["mean"]
    )
    light, _, heavy = (e["correction_mean"] for e in estimate["episodes"])
    # The estimate's share of the thrust scales with the cargo's mass (about 20x from 1 to 20 kg).
    assert 0 < light and heavy > 5 * light
    for e in estimate["episodes"] + none["episodes"]:
        assert e["correction_p95"] >= e["correction_mean"]


def test_train_parses_tasks_and_the_residual(capsys, tmp_path):
    train = load_script("train")
    out = str(tmp_path)
    args = train.parse_args(["--residual-scale", "0.3", "--env", "w_info=2.0", "--log-dir", out])
    kwargs = train.env_kwargs(args)
    assert kwargs["cargo_mass_kg"] == LEARNING_TASKS["cargo"]["cargo_mass_kg"]
    assert kwargs["residual_scale"] == 0.3 and kwargs["action_repeat"] == 5
    assert kwargs["w_info"] == 2.0 and kwargs["estimators"]
    # An information reward keeps the estimators running when they are not observed.
    args = train.parse_args(["--task", "excitation", "--no-estimates", "--log-dir", out])
    kwargs = train.env_kwargs(args)
    assert kwargs["estimators"] and not kwargs["observe_estimates"]
    args = train.parse_args(["--task", "cargo", "--no-estimates", "--log-dir", out])
    assert not train.env_kwargs(args)["estimators"]
    # The estimate base reads the estimates: they run and are observed, hidden from the policy.
    argv = ["--residual-scale", "0.3", "--base-model", "estimate", "--no-estimates"]
    kwargs = train.env_kwargs(train.parse_args(argv + ["--log-dir", out]))
    assert kwargs["base_model"] == "estimate" and kwargs["estimators"]
    assert kwargs["observe_estimates"] and kwargs["hide_estimates"]
    kwargs = train.env_kwargs(train.parse_args(argv[:4] + ["--log-dir", out]))
    assert kwargs["observe_estimates"] and not kwargs["hide_estimates"]
    with pytest.raises(SystemExit):
        train.parse_args(["--base-model", "estimate", "--log-dir", out])
    assert "--residual-scale > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train.parse_args(["--backend", "rllib", "--residual-scale", "0.3", "--log-dir", out])
    assert "no residual, no action repeat" in capsys.readouterr().err
    # The feed-forward input: from the live estimate, or from the prior without the estimates.
    argv = ["--residual-scale", "1.0", "--feedforward-obs", "--log-dir", out]
    assert train.env_kwargs(train.parse_args(argv))["feedforward_obs"] == "estimate"
    kwargs = train.env_kwargs(train.parse_args(argv + ["--no-estimates"]))
    assert kwargs["feedforward_obs"] == "prior" and not kwargs["observe_estimates"]
    assert train.env_kwargs(train.parse_args(argv[:2] + argv[3:]))["feedforward_obs"] is None


# --------------------------------------------------------------------------- imitation


def test_teacher_label_makes_the_base_the_teacher():
    """With one control step per decision the label, sent as the residual, gives the env the
    teacher's thrust (clipped as the env clips it); it is zero when the teacher is the base."""
    from astrocargo.envs.decision import residual_actions

    kwargs = {**FAST, "max_cycles": 8, "observe_estimates": True, "estimators": True}
    kwargs["cargo_mass_kg"] = (15.0, 15.0)  # heavy: the estimate changes the thrust
    env = cargo_env_fn(residual_scale=0.5, teacher_model="estimate", **kwargs)()
    same = cargo_env_fn(residual_scale=0.5, teacher_model="none", **kwargs)()
    obs, _ = env.reset(seed=2)
    same.reset(seed=2)
    teacher = ObservationController.for_env(env, "estimate")
    zeros = dict.fromkeys(env.possible_agents, np.zeros(6))
    differs = False
    while env.agents:
        wanted = teacher.predict({a: env._obs[a] for a in env.agents})[0]
        now = env.teacher_residual_now()
        _, _, _, _, infos = env.step(now)
        _, _, _, _, same_infos = same.step(zeros)
        for a, info in infos.items():
            np.testing.assert_allclose(info["teacher_residual"], now[a], atol=1e-12)
            sent = residual_actions(info["base_action"], info["teacher_residual"], 0.5)
            np.testing.assert_allclose(sent[:6], np.clip(wanted[a][:6], -1, 1), atol=1e-12)
            np.testing.assert_array_equal(same_infos[a]["teacher_residual"], np.zeros(6))
            differs |= bool(np.any(np.abs(now[a]) > 1e-5))
    assert differs  # the teacher is not the base: the label is not trivially zero


def test_teacher_label_is_the_mean_over_the_decision():
    kwargs = {**FAST, "max_cycles": 9, "observe_estimates": True, "estimators": True}
    env = cargo_env_fn(residual_scale=1.0, action_repeat=3, teacher_model="estimate", **kwargs)()
    env.reset(seed=1)
    action = dict.fromkeys(env.possible_agents, np.full(6, 0.05))
    per_step = []
    env.step(action)  # the estimate moves off the prior
    original = env.env.step

    def recording_step(sent):
        per_step.append(env.teacher_residual_now())
        return original(sent)

    env.env.step = recording_step
    _, _, _, _, infos = env.step(action)
    assert len(per_step) == 3
    for a, info in infos.items():
        np.testing.assert_allclose(
            info["teacher_residual"], np.mean([s[a] for s in per_step], axis=0), atol=1e-12
        )


def test_regression_fit_reduces_the_loss_of_the_actor_mean():
    from stable_baselines3 import PPO

    from astrocargo.agents import imitation

    venv = make_vec_env(1, seed=0, residual_scale=1.0, **FAST)
    model = PPO("MlpPolicy", venv, policy_kwargs={"net_arch": [64, 64]}, device="cpu", seed=0)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(512, venv.observation_space.shape[0]))
    y = np.tanh(0.3 * x[:, :6] * x[:, 6:12])  # a product of inputs, as the correction is
    losses = imitation.fit_regression(
        imitation.actor_mean(model.policy),
        imitation.actor_params(model.policy),
        x,
        y,
        100,
        batch_size=64,
    )
    assert losses[-1] < 0.2 * losses[0]
    critic_before = [p.detach().clone() for p in imitation.critic_params(model.policy)]
    assert all(
        np.array_equal(a.numpy(), b.detach().numpy())
        for a, b in zip(critic_before, imitation.critic_params(model.policy), strict=True)
    )  # the actor's fit leaves the critic alone
    venv.close()


def test_discounted_and_running_returns_restart_per_track():
    from astrocargo.agents import imitation

    reward, track = np.array([1.0, 2.0, 3.0, 4.0]), np.array([0, 0, 1, 1])
    np.testing.assert_allclose(
        imitation.discounted_returns(reward, track, 0.5, tail=np.array([0, 10.0, 0, 2.0])),
        [1 + 0.5 * (2 + 5), 2 + 5, 3 + 0.5 * (4 + 1), 4 + 1],
    )
    np.testing.assert_allclose(imitation.running_returns(reward, track, 0.5), [1, 2.5, 3, 5.5])


def test_imitation_run_saves_a_policy_that_evaluates_and_fine_tunes(tmp_path):
    """scripts/imitate.py: fits the label (loss falls), saves what evaluate.py loads and acts
    with, and train.py --init-from starts PPO from exactly those weights and statistics."""
    import torch

    imitate, train, evaluate = (load_script(n) for n in ("imitate", "train", "evaluate"))
    common = ["--max-cycles", "30", "--noise", "ideal", "--seed", "3", "--copies", "1"]
    common += ["--residual-scale", "1.0", "--action-repeat", "3", "--feedforward-obs"]
    common += ["--env", "cargo_mass_kg=(12.0, 18.0)"]
    run = tmp_path / "bc"
    assert (
        imitate.main(
            common
            + ["--episodes", "2", "--dagger-episodes", "1"]
            + ["--fit-epochs", "30", "--log-dir", str(run)]
        )
        == 0
    )
    config = json.loads((run / "config.json").read_text())
    mse = config["imitation"]["actor_mse"]
    assert len(mse) == 2 and mse[0][1] < 0.5 * mse[0][0]
    assert config["imitation"]["labelled_samples"] == 3 * 2 * 10
    assert "imitation" in load_script("eval_report").arm_key(config)
    policy = evaluate.TrainedPolicy(run)
    assert float(policy.model.policy.log_std.detach().mean()) == pytest.approx(-2.5)
    decision = ("residual_scale", "action_repeat", "base_model", "hide_estimates")
    decision += ("feedforward_obs",)
    kwargs = {k: v for k, v in config["env_kwargs"].items() if k not in decision}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    obs, _ = env.reset(seed=0)
    policy.reset(env)
    assert policy.act(np.stack(list(obs.values()))).shape == (2, 8)
    tuned = tmp_path / "ft"
    args = train.parse_args(
        common
        + ["--timesteps", "32", "--init-from", str(run), "--log-dir", str(tuned)]
        + ["--no-progress-bar", "--hyperparams", "n_steps=16", "batch_size=16", "n_epochs=1"]
    )
    model, _ = train.build_model(args, 3, None)
    train.initialise_from(model, run)
    for name, value in model.policy.state_dict().items():
        torch.testing.assert_close(value, policy.model.policy.state_dict()[name])
    np.testing.assert_array_equal(model.get_env().obs_rms.mean, policy.normalizer.obs_rms.mean)
    other = tmp_path / "other"
    with pytest.raises(SystemExit):  # another arm's env cannot start from this run
        train.parse_args(
            [*common, "--no-estimates", "--init-from", str(run), "--log-dir", str(other)]
        )


def test_masked_block_no_longer_reaches_the_policy(trained_runs):
    evaluate = load_script("evaluate")
    plain, masked = (evaluate.TrainedPolicy(trained_runs / "res") for _ in range(2))
    masked.mask("peer0_wrench")
    assert "peer0_wrench masked" in load_script("eval_report").arm_key(masked.config)
    kwargs = {k: v for k, v in plain.config["env_kwargs"].items() if k in FAST or k == "n_robots"}
    env = astrobee_cargo_v0.parallel_env(**kwargs)
    obs, _ = env.reset(seed=0)
    obs = np.stack(list(obs.values()))
    for policy in (plain, masked):
        policy.reset(env)
    pushed = obs.copy()
    pushed[:, env.sim.obs_layout["peer0_wrench"]] += 5.0
    np.testing.assert_array_equal(masked.decide(obs), masked.decide(pushed))
    assert np.any(plain.decide(obs) != plain.decide(pushed))  # the block matters unmasked
    masked.masked = "no_such_block"
    with pytest.raises(ValueError, match="no observation block"):
        masked.reset(env)


def test_hidden_estimators_run_them_unseen_and_keep_the_policy_view(tmp_path):
    """--hidden-estimators: the estimators run (the peers' messages fill the observation, as in
    evaluation) but the policy does not see them: the same policy view as --no-estimates."""
    train = load_script("train")
    common = ["--residual-scale", "1.0", "--feedforward-obs", "--no-estimates"]
    common += ["--log-dir", str(tmp_path / "run")]
    plain = train.env_kwargs(train.parse_args(common))
    hidden = train.env_kwargs(train.parse_args([*common, "--hidden-estimators"]))
    assert not plain["estimators"] and not plain["observe_estimates"]
    assert hidden["estimators"] and hidden["observe_estimates"] and hidden["hide_estimates"]
    assert hidden["feedforward_obs"] == plain["feedforward_obs"] == "prior"
    assert train.policy_env(hidden) == train.policy_env(plain)
    seen = train.env_kwargs(train.parse_args(common[:-3] + common[-2:]))  # estimates observed
    assert train.policy_env(seen) != train.policy_env(plain)
