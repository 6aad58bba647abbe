"""The encoders' squared rate noise (``momentum`` module docstring, Filters): Q's products of
the joint rates square the encoders' noise, whose fluctuation about its subtracted mean enters
the balance. Its per-update variance (``rate_square_var``) scales the terms of
``momentum.rate_square_terms``; with motion fusion they are modes of the instant
(``NoiseModel.instant_modes``), without it their links' part goes with the message
(``rate_square_links_cov``) and the regressor's waits with the instant.
"""

from __future__ import annotations

import numpy as np

from .preprocess import StateVariableFilter


def rate_square_var(
    dt_s: float, rate_cutoff_hz: float, encoder_std_rad: float, update_every: int
) -> float:
    """Per-update white-equivalent variance (rad/s)^4 of n^2 - E n^2, n the encoders' white
    noise (std s per sample) through the momentum form's rate filter's derivative (``momentum``:
    Q's products of joint rates square it). With h the filter's derivative impulse response and
    r(d) = sum_m h_m h_m+d, n^2 has the autocovariance 2 s^4 r(d)^2 (Gaussian), flat in the
    band below the slow filter's cutoff, where the chain's gain is 1: per update
    S(0) / (2 dt_update) = s^4 sum_d r(d)^2 / update_every (times 2 for a square, 1 for a
    product of two joints' noises: ``momentum.rate_square_terms``)."""
    rate = StateVariableFilter(1, dt_s, rate_cutoff_hz)
    rate.step(np.zeros(1))
    n = int(np.ceil(40 * rate.delay_s / dt_s)) + 8
    h = np.array([rate.step(np.array([float(k == 0)]))[1][0] for k in range(n)])
    r = np.correlate(h, h, mode="full")
    return float(encoder_std_rad**4 * np.sum(r**2) / update_every)


def rate_square_links_cov(rate_terms, rate_var: float, update_every: int) -> np.ndarray:
    """The links' part (6, 6) of the squared rate noise ``rate_terms`` (terms, weights of
    ``momentum.rate_square_terms``) at ``rate_var`` (rad/s)^4 per update (``rate_square_var``),
    times ``update_every``: it goes with the message as the actuation's does (per step: the
    receiver divides by update_every). Zero for None."""
    if rate_terms is None:
        return np.zeros((6, 6))
    terms, weights = rate_terms
    links = terms[:, 12:18]
    return update_every * rate_var * ((links.T * weights) @ links)
