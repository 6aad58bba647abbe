"""``AstrobeeCargoEnv.step_arrays`` (the SB3 adapter's path) against ``step`` (dicts)."""

from __future__ import annotations

import numpy as np
import pytest

from astrocargo.envs import astrobee_cargo_v0


def _actions(n_robots: int, k: int) -> np.ndarray:
    phase = np.arange(n_robots * 8).reshape(n_robots, 8)
    return 0.3 * np.sin(0.05 * k + phase)


def _same_info(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert a[key] == b[key], key


@pytest.mark.parametrize(
    ("kwargs", "n_steps"),
    [
        ({"n_robots": 2, "max_cycles": 12}, 12),  # truncated at max_cycles
        ({"n_robots": 3, "max_cycles": 40, "release_at": [(1, 0.1)]}, 40),  # robot 1 lets go
    ],
    ids=["truncation", "release"],
)
def test_step_arrays_equals_step(kwargs, n_steps):
    """Seeded alike, the array step gives the dict step's observations, rewards, terminations,
    truncations and infos in robot index order, and the same agents stay live; robots not live
    at a step's start get zeros, False and None."""
    by_dict = astrobee_cargo_v0.parallel_env(noise="nominal", **kwargs)
    by_array = astrobee_cargo_v0.parallel_env(noise="nominal", **kwargs)
    by_dict.reset(seed=3)
    by_array.reset(seed=3)
    agents = by_dict.possible_agents
    released_seen = False
    for k in range(n_steps):
        live = list(by_dict.agents)
        actions = _actions(len(agents), k)
        obs, rewards, terms, truncs, infos = by_dict.step(
            {a: actions[i] for i, a in enumerate(agents) if a in live}
        )
        step = by_array.step_arrays(actions)
        assert by_array.agents == by_dict.agents
        for i, a in enumerate(agents):
            if a in live:
                np.testing.assert_array_equal(step.observations[i], obs[a])
                assert step.rewards[i] == rewards[a]
                assert step.terminated[i] == terms[a] and step.truncated[i] == truncs[a]
                _same_info(step.infos[i], infos[a])
            else:
                released_seen = True
                assert not step.observations[i].any() and step.rewards[i] == 0.0
                assert not step.terminated[i] and not step.truncated[i]
                assert step.infos[i] is None
    assert not by_array.agents and not by_dict.agents  # both ended at max_cycles
    assert released_seen == ("release_at" in kwargs)
    with pytest.raises(RuntimeError):
        by_array.step_arrays(_actions(len(agents), 0))


def test_step_arrays_rejects_bad_actions():
    env = astrobee_cargo_v0.parallel_env(n_robots=2, noise="nominal")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step_arrays(np.zeros((2, 7)))
    bad = np.zeros((2, 8))
    bad[1, 3] = np.nan
    with pytest.raises(ValueError, match="robot 1"):
        env.step_arrays(bad)
