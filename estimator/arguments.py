"""The argument checks of ``CargoEstimator`` (``cargo_estimator``): each constructor argument in
its range, the fused motion's lag in control steps and the NIS gate of ``gate_prob``."""

from __future__ import annotations

import functools

import numpy as np
from scipy.stats import chi2

from .noise_model import MOTION_FUSION


def check_arguments(
    index, peers, update_every, regressor_every, warmup_s, history_s, gate_prob,
    min_excitation_snr, process_std_rel, min_relative_fixes, motion_fusion,
) -> None:  # fmt: skip
    """Raise ValueError for a constructor argument of ``CargoEstimator`` out of its range (the
    noise model's arguments: ``NoiseModel``)."""
    if motion_fusion not in MOTION_FUSION:
        raise ValueError(f"motion_fusion must be one of {MOTION_FUSION}, got {motion_fusion!r}")
    if regressor_every < 1 or update_every < 1 or update_every % regressor_every:
        raise ValueError(
            f"update_every ({update_every}) must be a positive multiple of regressor_every "
            f"({regressor_every})"
        )
    if index in peers:
        raise ValueError(f"robot {index} cannot be its own peer")
    if not (np.isfinite(warmup_s) and warmup_s >= 0):
        raise ValueError(f"warmup_s must be a finite number >= 0 s, got {warmup_s!r}")
    if not (np.isfinite(history_s) and history_s > 0):
        raise ValueError(f"history_s must be a finite number > 0 s, got {history_s!r}")
    if gate_prob is not None and not 0 < gate_prob < 1:
        raise ValueError(f"gate_prob must be None or a probability in (0, 1), got {gate_prob!r}")
    if not (np.isfinite(min_excitation_snr) and min_excitation_snr >= 0):
        raise ValueError(f"min_excitation_snr must be finite and >= 0, got {min_excitation_snr!r}")
    if not (np.isfinite(process_std_rel) and process_std_rel >= 0):
        raise ValueError(f"process_std_rel must be finite and >= 0, got {process_std_rel!r}")
    if min_relative_fixes < 1:
        raise ValueError(f"min_relative_fixes must be >= 1, got {min_relative_fixes}")


def motion_lag_steps(motion_lag_s, dt_s, localization_every) -> int:
    """``motion_lag_s`` in control steps (0: off); ValueError unless finite, >= 0 and, when
    positive, at least one control step; ``localization_every`` must be >= 1."""
    if not (np.isfinite(motion_lag_s) and motion_lag_s >= 0):
        raise ValueError(f"motion_lag_s must be a finite number >= 0 s, got {motion_lag_s!r}")
    if localization_every < 1:
        raise ValueError(f"localization_every must be >= 1, got {localization_every}")
    steps = int(round(motion_lag_s / dt_s))
    if motion_lag_s > 0 and steps < 1:
        raise ValueError(f"motion_lag_s must be 0 or at least one control step ({dt_s} s)")
    return steps


@functools.lru_cache(maxsize=16)
def nis_gate(gate_prob: float) -> float:
    """The NIS gate of a 6-component wrench: the chi-square(6) quantile of ``gate_prob`` (computed
    once per probability: scipy's quantile takes longer than building the rest of the UKF)."""
    return float(chi2.ppf(gate_prob, 6))
