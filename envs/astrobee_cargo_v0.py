"""astrobee_cargo_v0: N Astrobees carry one cargo of unknown inertia (see
``astrocargo.envs.cargo_transport`` for the full description).

Exports, as PettingZoo environments do:

- ``parallel_env(**kwargs)``: the ParallelEnv (``AstrobeeCargoEnv``);
- ``raw_env(**kwargs)``: the AEC form, ``pettingzoo.utils.parallel_to_aec`` of it (which already
  applies ``OrderEnforcingWrapper``);
- ``env(**kwargs)``: the same AEC env (no further wrapper: actions are clipped and validated
  by the environment itself).
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils import parallel_to_aec
from pettingzoo.utils.env import AECEnv

from astrocargo.envs.cargo_transport import AstrobeeCargoEnv


def parallel_env(**kwargs: Any) -> AstrobeeCargoEnv:
    """The parallel environment; keyword arguments as ``AstrobeeCargoEnv``."""
    return AstrobeeCargoEnv(**kwargs)


def raw_env(**kwargs: Any) -> AECEnv:
    """The AEC environment (``parallel_to_aec``, order-enforcing)."""
    return parallel_to_aec(parallel_env(**kwargs))


def env(**kwargs: Any) -> AECEnv:
    """The AEC environment, as PettingZoo's ``env()`` convention asks."""
    return raw_env(**kwargs)


__all__ = ["AstrobeeCargoEnv", "env", "parallel_env", "raw_env"]
