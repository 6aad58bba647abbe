"""astrocargo.envs: the MuJoCo world, sensors, communication channel and the PettingZoo env.

``from astrocargo.envs import astrobee_cargo_v0`` imports the environment module (and MuJoCo)
only when asked for; importing the package itself loads nothing heavy.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY_MODULES = ("astrobee_cargo_v0", "cargo_transport", "comms", "sensors", "world")


def __getattr__(name: str) -> Any:
    if name in _LAZY_MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_LAZY_MODULES)
