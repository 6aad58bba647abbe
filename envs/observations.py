"""The observation layout: one table of blocks (name, size) from which both the observation
space and each robot's observation row are built."""

from __future__ import annotations

import numpy as np


def observation_layout(n_robots: int, observe_estimates: bool = True) -> dict[str, slice]:
    """Index slices of each observation block (see the module docstring's table)."""
    sizes = [
        ("base_pos_err", 3),
        ("base_vel_err", 3),
        ("base_att_err", 3),
        ("base_ang_vel", 3),
        ("joint_pos", 2),
        ("joint_target", 2),
        ("ref_pos_rel", 3),
        ("ref_vel", 3),
        ("ref_acc", 3),
        ("ref_ang_vel", 3),
        ("ref_ang_acc", 3),
        ("ref_pan", 2),
    ]
    for p in range(n_robots - 1):
        sizes += [(f"peer{p}_wrench", 6), (f"peer{p}_age", 1), (f"peer{p}_valid", 1)]
    if observe_estimates:
        sizes += [("estimate_mean", 10), ("estimate_std", 10)]
    out, start = {}, 0
    for name, size in sizes:
        out[name] = slice(start, start + size)
        start += size
    out["all"] = slice(0, start)
    return out


def observation_bounds(layout: dict[str, slice]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the observation space: the valid flags in [0, 1], the rest
    unbounded."""
    size = layout["all"].stop
    low, high = np.full(size, -np.inf), np.full(size, np.inf)
    for name, sl in layout.items():
        if name.endswith("_valid"):
            low[sl], high[sl] = 0.0, 1.0
    return low, high
