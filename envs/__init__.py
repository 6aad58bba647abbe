"""astrocargo.envs: the MuJoCo world, sensors, communication channel and the PettingZoo env.

``from astrocargo.envs import astrobee_cargo_v0`` imports the environment module (and MuJoCo)
only when asked for. Importing the package itself loads only Gymnasium, to register the
single-agent form as ``ENV_ID``, so that ``import astrocargo.envs`` then
``gymnasium.make("astrocargo/AstrobeeCargo-v0")`` works, as with other environment packages
(the ``module:ID`` form, ``gymnasium.make("astrocargo.envs:astrocargo/AstrobeeCargo-v0")``,
imports this package and so works too).
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium

ENV_ID = "astrocargo/AstrobeeCargo-v0"
if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="astrocargo.envs.wrappers:CentralizedCargoEnv")

_LAZY_MODULES = (
    "astrobee_cargo_v0",
    "cargo_transport",
    "comms",
    "sensors",
    "world",
    "wrappers",
)


def __getattr__(name: str) -> Any:
    if name in _LAZY_MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["ENV_ID", *_LAZY_MODULES]
