"""The env leaves its process in one piece: copies (deepcopy, pickle) continue bit for bit,
human rendering without a display raises instead of ending the interpreter, and importing
``astrocargo.envs`` registers the Gymnasium form (issue #13, items 5-7)."""

from __future__ import annotations

import copy
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from astrocargo.envs import astrobee_cargo_v0

FAST = {"n_robots": 2, "control_hz": 12.5, "max_cycles": 400}


def _actions(env, k: int) -> dict[str, np.ndarray]:
    phase = np.arange(8) + 3.0 * np.arange(len(env.possible_agents))[:, None]
    a = 0.3 * np.sin(0.2 * k + phase)
    return {agent: a[int(agent.rsplit("_", 1)[1])] for agent in env.agents}


def _run_alongside(envs, first_step: int, n_steps: int) -> None:
    for k in range(first_step, first_step + n_steps):
        actions = _actions(envs[0], k)
        results = [e.step(actions) for e in envs]
        obs0, rew0, term0, trunc0, infos0 = results[0]
        for obs, rew, term, trunc, infos in results[1:]:
            assert obs.keys() == obs0.keys()
            for agent in obs0:
                assert np.array_equal(obs[agent], obs0[agent]), (k, agent)
                assert rew[agent] == rew0[agent]
                assert term[agent] == term0[agent] and trunc[agent] == trunc0[agent]
                if "estimate" in infos0[agent]:
                    assert np.array_equal(infos[agent]["estimate"], infos0[agent]["estimate"])
        states = [e.state() for e in envs]
        for s in states[1:]:
            assert np.array_equal(s, states[0]), k


ESTIMATORS = [
    pytest.param({"estimators": False, "observe_estimates": False}, id="no-estimators"),
    pytest.param({}, id="estimators"),
]


@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
@pytest.mark.parametrize("estimators", ESTIMATORS)
def test_copy_mid_episode_continues_bit_identically(how, estimators):
    env = astrobee_cargo_v0.parallel_env(
        **FAST,
        **estimators,
        faults=[{"kind": "comm_burst", "robot": 1, "start_s": 3.0, "duration_s": 2.0, "prob": 0.5}],
    )
    env.reset(seed=11)
    for k in range(30):
        env.step(_actions(env, k))
    twin = copy.deepcopy(env) if how == "deepcopy" else pickle.loads(pickle.dumps(env))
    assert twin.sim.data is not env.sim.data
    _run_alongside([env, twin], 30, 100)
    # The copy's views write into its own MjData, not into the original's.
    twin.sim._ctrl[:] = 0.0
    assert np.shares_memory(twin.sim._ctrl, twin.sim.data.ctrl)
    assert not np.shares_memory(twin.sim._ctrl, env.sim.data.ctrl)


def test_copy_after_release_and_reset_continues():
    env = astrobee_cargo_v0.parallel_env(
        n_robots=3,
        control_hz=12.5,
        max_cycles=200,
        release_at=[(2, 1.0)],
        estimators=False,
        observe_estimates=False,
    )
    env.reset(seed=4)
    for k in range(20):  # robot 2 lets go at step 13: the world was rebuilt
        env.step(_actions(env, k))
    assert env.agents == ["astrobee_0", "astrobee_1"]
    twin = pickle.loads(pickle.dumps(env))
    _run_alongside([env, twin], 20, 30)
    for e in (env, twin):
        e.reset(seed=5)
    _run_alongside([env, twin], 0, 20)


def test_copy_drops_a_live_renderer(monkeypatch):
    env = astrobee_cargo_v0.parallel_env(**FAST, render_mode="rgb_array")
    env.reset(seed=0)
    env._renderer = object()  # stands for a live GL context, which cannot be copied
    twin = copy.deepcopy(env)
    assert twin._renderer is None and twin._viewer is None
    assert env._renderer is not None


def test_supersuit_vector_path():
    ss = pytest.importorskip("supersuit")
    env = astrobee_cargo_v0.parallel_env(**FAST)
    vec = ss.pettingzoo_env_to_vec_env_v1(env)
    vec = ss.concat_vec_envs_v1(vec, 2, num_cpus=0, base_class="stable_baselines3")
    obs = vec.reset()
    assert obs.shape == (4, env.observation_space("astrobee_0").shape[0])
    obs, rewards, dones, infos = vec.step(np.zeros((4, 8), dtype=np.float32))
    assert np.isfinite(obs).all() and rewards.shape == (4,)
    vec.close()


def test_human_render_without_display_raises(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check concerns X11 / Wayland")
    with pytest.raises(RuntimeError, match="needs a display"):
        astrobee_cargo_v0.parallel_env(**FAST, render_mode="human")


def _fresh_python(code: str, **env_vars: str | None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    for key, value in env_vars.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="X11 / Wayland only")
def test_human_render_without_display_keeps_the_interpreter():
    code = (
        "from astrocargo.envs import astrobee_cargo_v0\n"
        "try:\n"
        "    env = astrobee_cargo_v0.parallel_env(n_robots=1, render_mode='human')\n"
        "    env.reset(seed=0)\n"
        "except RuntimeError as err:\n"
        "    print('raised:', err)\n"
        "print('alive')\n"
    )
    done = _fresh_python(code, DISPLAY=None, WAYLAND_DISPLAY=None)
    assert done.returncode == 0, done.stderr
    assert 'raised: render_mode="human" needs a display' in done.stdout
    assert done.stdout.rstrip().endswith("alive")


@pytest.mark.parametrize(
    "make",
    [
        "import astrocargo.envs, gymnasium\nenv = gymnasium.make(ENV_ID, **KW)",
        "import gymnasium\nenv = gymnasium.make('astrocargo.envs:' + ENV_ID, **KW)",
        "import gymnasium\nenv = gymnasium.make('astrocargo.envs.wrappers:' + ENV_ID, **KW)",
    ],
)
def test_gymnasium_registration_in_a_fresh_process(make):
    code = (
        "ENV_ID = 'astrocargo/AstrobeeCargo-v0'\n"
        "KW = dict(n_robots=1, control_hz=12.5, max_cycles=5, estimators=False,"
        " observe_estimates=False)\n"
        f"{make}\n"
        "obs, info = env.reset(seed=0)\n"
        "assert obs.shape == env.observation_space.shape, obs.shape\n"
        "print('made', type(env.unwrapped).__name__)\n"
    )
    done = _fresh_python(code)
    assert done.returncode == 0, done.stderr
    assert "made CentralizedCargoEnv" in done.stdout


def test_importing_the_package_stays_light():
    code = (
        "import sys, astrocargo.envs\n"
        "heavy = [m for m in ('mujoco', 'pettingzoo', 'stable_baselines3', 'numba')"
        " if m in sys.modules]\n"
        "print('heavy:', heavy)\n"
    )
    done = _fresh_python(code)
    assert done.returncode == 0, done.stderr
    assert "heavy: []" in done.stdout
