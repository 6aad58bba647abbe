"""The env's one configuration: every argument of ``AstrobeeCargoEnv`` (and of the plain
``CargoTransport`` under it) with its default, validated once. The table of arguments is in the
env module's docstring (``astrocargo.envs.cargo_transport``, section Arguments)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from astrocargo.agents.excitation import check_trajectory
from astrocargo.envs.faults import Fault, parse_faults
from astrocargo.envs.sensors import NOISE_PROFILES
from astrocargo.envs.validation import check_choice, check_finite_array, check_finite_number
from astrocargo.envs.world import MAX_ROBOTS

CONTROL_HZ = 62.5  # Astrobee GNC and PMC rate (sources §3.1, docs/design.md)
EPISODE_S = 90.0  # default episode length: the seed paper's runs last 90 s
# Accepted cargo masses: an empty bag (ISAAC's cargo model's 0.5 kg, sources §7) to
# ten Astrobees' worth; beyond that two robots' 0.4 N cannot move it within an episode.
CARGO_MASS_LIMITS_KG = (0.1, 100.0)
CONTROL_HZ_LIMITS = (10.0, 1000.0)  # estimator filters need >= 10 Hz (1 Hz pre-filter cutoff)
MAX_REWARD_WEIGHT = 1e6  # keeps every weighted term finite
MAX_COMM_LATENCY_S = 60.0  # far beyond the estimators' history (2 s): nothing then arrives in time
MAX_COMM_NOISE = (10.0, 1.0)  # force N, moment N m: 25 times the propulsion limits
RENDER_MODES = ("rgb_array", "human")
RENDER_CAMERA_TRACK = "track"
MAX_RENDER_SIZE = {"render_width": 1280, "render_height": 720}  # the MJCF's offscreen buffer
REWARD_TERMS = ("track", "effort", "info", "contact")

# The learning tasks of scripts/train.py and evaluate.py (``--task NAME``): keyword arguments of
# ``cargo_env_fn`` (those of ``astrobee_cargo_v0.parallel_env`` plus ``action_repeat``, the control
# steps per decision of the policy). docs/learning.md gives the measurements behind each choice.
LEARNING_TASKS: dict[str, dict[str, Any]] = {
    # The first task: the first 10 s of the figure-eight (the reference starts moving from rest),
    # the default 5 kg cargo (only its centre of mass drawn), the env and the policy at 12.5 Hz:
    # 125 decisions. Too short for the mass estimate to converge, and at 12.5 Hz the estimators
    # stall (docs/learning.md).
    "figure8_10s": {
        "trajectory": "figure8_yaw",
        "control_hz": 12.5,
        "max_cycles": 125,
        "noise": "nominal",
        "action_repeat": 1,
    },
    # The cargo varies: its mass uniform in [1, 20] kg at each reset (centre of mass uniform in
    # +-3 cm, inertia that of a uniform box of the bag's size and the drawn mass); 30 s of the
    # figure-eight; the env (scripted feedback, estimators) at the GNC rate 62.5 Hz, the policy
    # deciding at 12.5 Hz (every fifth control step): 375 decisions. The scripted controller's
    # mass estimate is within 5 % by about 6 s for 5-20 kg.
    "cargo": {
        "trajectory": "figure8_yaw",
        "control_hz": 62.5,
        "max_cycles": 1875,
        "noise": "nominal",
        "cargo_mass_kg": (1.0, 20.0),
        "action_repeat": 5,
    },
    # Learned excitation: 90 s of the tumbling figure-eight (the flight time of the designed
    # ``excite`` trajectory), the default 5 kg cargo, the information reward (decrease of the
    # estimate's sum(log std) per step) with tracking (the leash that keeps the cargo in the
    # aisle) and a strong contact penalty; 62.5 Hz env, decisions at 12.5 Hz. Weights: with the
    # env's defaults (w_info 1, w_effort 0.01) the scripted controller's 90 s on ``excite`` score
    # below those on the tumble (information +4 against effort -29); w_info 10 and w_effort
    # 0.001 rank the more informative flight first (docs/learning.md).
    "excitation": {
        "trajectory": "figure8_tumble",
        "control_hz": 62.5,
        "max_cycles": 5625,
        "noise": "nominal",
        "w_info": 10.0,
        "w_effort": 0.001,
        "w_contact": 10.0,
        "action_repeat": 5,
    },
}


@dataclass(frozen=True)
class EnvConfig:
    """Arguments of the env, validated at construction (``ValueError``); see the env module's
    Arguments table. Checks that need the built world (cargo within its bag, ``frame_skip``
    against the MJCF timestep, ``render_camera`` among the model's cameras) are made where the
    world is built (``CargoTransport``, ``AstrobeeCargoEnv``)."""

    n_robots: int = 2
    trajectory: str = "figure8_yaw"
    fast: bool = False
    noise: str = "nominal"
    cargo_mass_kg: float | tuple[float, float] = 5.0
    cargo_com_m: tuple[float, float, float] | None = None
    cargo_inertia: tuple[float, float, float, float, float, float] | None = None
    comm_latency: float = 0.0
    comm_drop: float = 0.0
    comm_noise: tuple[float, float] = (0.0, 0.0)
    control_hz: float = CONTROL_HZ
    frame_skip: int | None = None
    max_cycles: int | None = None
    w_track: float = 1.0
    w_effort: float = 0.01
    w_info: float = 0.0
    w_contact: float = 1.0
    shared_reward: float = 1.0
    observe_estimates: bool = True
    estimators: bool = True
    estimator_kwargs: dict[str, Any] | None = None
    faults: list[dict[str, Any] | Fault] | tuple[Fault, ...] | None = None
    release_at: Any = None
    render_mode: str | None = None
    render_width: int = 640
    render_height: int = 480
    render_camera: str = RENDER_CAMERA_TRACK

    def __post_init__(self) -> None:
        self._check_robots_and_choices()
        self._check_rates()
        self._check_channel()
        self._check_rewards()
        self._check_rendering()
        if self.estimator_kwargs is not None and not isinstance(self.estimator_kwargs, dict):
            raise ValueError(
                f"estimator_kwargs must be a dict or None, got {self.estimator_kwargs!r}"
            )
        self._set("faults", parse_faults(self.faults, self.n_robots))

    def _set(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)  # normalise a field of the frozen config

    def replace(self, **changes: Any) -> EnvConfig:
        """A copy with ``changes`` applied, validated again."""
        return dataclasses.replace(self, **changes)

    def _check_robots_and_choices(self) -> None:
        n = self.n_robots
        if isinstance(n, bool) or not isinstance(n, int | np.integer):
            raise ValueError(f"n_robots must be an integer in 1..{MAX_ROBOTS}, got {n!r}")
        if not 1 <= n <= MAX_ROBOTS:
            raise ValueError(f"n_robots must be in 1..{MAX_ROBOTS}, got {n}")
        self._set("n_robots", int(n))
        for name in ("fast", "observe_estimates", "estimators"):
            flag = getattr(self, name)
            if not isinstance(flag, bool | np.bool_):
                raise ValueError(f"{name} must be True or False, got {flag!r}")
            self._set(name, bool(flag))
        check_trajectory(self.trajectory, self.n_robots, self.fast)
        check_choice("noise profile", self.noise, NOISE_PROFILES)
        if self.observe_estimates and not self.estimators:
            raise ValueError("observe_estimates=True needs estimators=True")

    def _check_rates(self) -> None:
        low_hz, high_hz = CONTROL_HZ_LIMITS
        allowed_hz = f"a number of Hz in [{low_hz}, {high_hz}]"
        control_hz = check_finite_number("control_hz", self.control_hz, allowed_hz)
        if not low_hz <= control_hz <= high_hz:
            raise ValueError(f"control_hz must be {allowed_hz}, got {control_hz}")
        self._set("control_hz", control_hz)
        for name in ("frame_skip", "max_cycles"):
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"{name} must be None or a positive integer, got {value!r}")
            if name == "max_cycles" and value < 1:  # frame_skip: checked with the timestep
                raise ValueError(f"{name} must be None or a positive integer, got {value}")
            self._set(name, int(value))

    def _check_channel(self) -> None:
        allowed = f"a latency in [0, {MAX_COMM_LATENCY_S}] s"
        latency = check_finite_number("comm_latency", self.comm_latency, allowed)
        if not 0.0 <= latency <= MAX_COMM_LATENCY_S:
            raise ValueError(f"comm_latency must be {allowed}, got {latency}")
        self._set("comm_latency", latency)
        allowed_noise = f"two numbers (force N, moment N m) in [0, {MAX_COMM_NOISE}]"
        noise_std = check_finite_array(
            "comm_noise (the channel's noise_std)", self.comm_noise, (2,), allowed_noise
        )
        if np.any(noise_std < 0) or np.any(noise_std > MAX_COMM_NOISE):
            raise ValueError(
                f"comm_noise (noise_std) must be {allowed_noise}, got {self.comm_noise!r}"
            )
        self._set("comm_noise", tuple(float(x) for x in noise_std))

    def _check_rewards(self) -> None:
        allowed_w = f"a number in [-{MAX_REWARD_WEIGHT:g}, {MAX_REWARD_WEIGHT:g}]"
        for term in REWARD_TERMS:
            weight = getattr(self, f"w_{term}")
            value = check_finite_number(f"w_{term}", weight, allowed_w)
            if abs(value) > MAX_REWARD_WEIGHT:
                raise ValueError(f"w_{term} must be {allowed_w}, got {weight}")
            self._set(f"w_{term}", value)
        shared = check_finite_number("shared_reward", self.shared_reward, "a number in [0, 1]")
        if not 0.0 <= shared <= 1.0:
            raise ValueError(f"shared_reward must be a number in [0, 1], got {self.shared_reward}")
        self._set("shared_reward", shared)

    def _check_rendering(self) -> None:
        if self.render_mode is not None and self.render_mode not in RENDER_MODES:
            raise ValueError(
                f"unknown render_mode {self.render_mode!r}; allowed: None, {list(RENDER_MODES)}"
            )
        for name, limit in MAX_RENDER_SIZE.items():
            size = getattr(self, name)
            if isinstance(size, bool) or not isinstance(size, int | np.integer):
                raise ValueError(f"{name} must be an integer in 1..{limit}, got {size!r}")
            if not 1 <= size <= limit:
                raise ValueError(f"{name} must be an integer in 1..{limit}, got {size}")
            self._set(name, int(size))

    @property
    def weights(self) -> dict[str, float]:
        """The reward weights by term (``REWARD_TERMS`` order)."""
        return {t: getattr(self, f"w_{t}") for t in REWARD_TERMS}
