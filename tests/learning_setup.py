"""What the learning tests share: the small env of their tiny trainings and the loader of the
scripts they drive (scripts/ is not a package)."""

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

# Tiny budgets: 20-step episodes, ideal noise, the estimators off.
FAST = {
    "n_robots": 2,
    "noise": "ideal",
    "max_cycles": 20,
    "observe_estimates": False,
    "estimators": False,
}


def load_script(name: str):
    """scripts/``name``.py as a module."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def rollout(venv, steps, seed=0):
    """Observations, rewards, dones of ``steps`` seeded random steps of a VecEnv (from reset)."""
    rng = np.random.default_rng(seed)
    out = [venv.reset()]
    for _ in range(steps):
        obs, rewards, dones, _ = venv.step(rng.uniform(-1, 1, (venv.num_envs, 8)))
        out += [obs, rewards, dones]
    return out
