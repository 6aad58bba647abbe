"""Ray glue shared by scripts/benchmark_estimation.py (--backend ray) and scripts/train.py
(--backend rllib): import Ray with an install hint, and connect for a block of work."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


def import_ray(purpose: str = "the Ray backend needs Ray"):
    """The ``ray`` module, or an ImportError saying that ``purpose`` needs it and how to install
    it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError(
            f"{purpose}: pip install 'astrocargo[ray]' (in a checkout: bash scripts/setup.sh "
            "--dev, or .venv/bin/python -m pip install -e '.[ray]')"
        ) from err
    return ray


@contextlib.contextmanager
def ray_connection(ray, address: str | None) -> Iterator[None]:
    """Connect to the Ray cluster at ``address`` (None: start a local instance) for the block;
    a connection this process already has is used and left open."""
    if ray.is_initialized():
        yield
        return
    # Workers on other nodes do not inherit this shell: pass the rendering backend and the BLAS
    # thread count (both scripts set it: threads only add hand-offs on these small matrices).
    env_vars = {
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1"),
    }
    ray.init(address=address or "local", runtime_env={"env_vars": env_vars})
    try:
        yield
    finally:
        ray.shutdown()
