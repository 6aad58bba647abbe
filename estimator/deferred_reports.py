"""What the estimator reports beside its filter's own (x, P), built from the used updates and
deferred (the filter's path untouched): the errors-in-variables compensation of the estimate
(``bias_compensation``) and the encoders' correlation over updates in its covariance
(``encoder_covariance``), for the filter without an over-time window. The compensation is off
by default (``CargoEstimator(bias_compensation=True)``); the encoders' covariance is on by
default wherever its derivation holds (no window, no random walk; ``encoders_over_time=None``)."""

from __future__ import annotations

import numpy as np

from .bias_compensation import DeferredCompensation, own_modes
from .copies import deepcopy_state
from .encoder_covariance import EncoderCovariance


class DeferredReports:
    """The deferred reports that are on, fed each used update's own modes (``modes``, ``add``)
    and restored with the filter on a rollback (``state``, ``restore``)."""

    __deepcopy__ = deepcopy_state  # copies as copy.deepcopy does (``copies``)

    def __init__(
        self, noise, update_every: int, compensate: bool, over_time: bool, rollback: int = 0
    ) -> None:
        self.noise, self.update_every = noise, int(update_every)
        self.compensation = DeferredCompensation() if compensate else None
        self.encoder_cov = EncoderCovariance.of(noise, rollback) if over_time else None
        self._reports = tuple(r for r in (self.compensation, self.encoder_cov) if r is not None)

    @classmethod
    def of(cls, noise, update_every, compensate, over_time, window, walk, rollback: int = 0):
        """The reports asked for, or None; ValueError with a window or (``over_time``) a
        random walk ``walk`` Q != 0 (their derivations assume neither). ``over_time`` None: on
        without a window and a walk, else off. ``rollback``: the most updates a ``restore``
        undoes (the estimator's snapshots)."""
        if over_time is None:
            over_time = not window and not np.any(walk)
        if not (compensate or over_time):
            return None
        if window:
            raise ValueError("bias_compensation and encoders_over_time need over_time_window 0")
        if over_time and np.any(walk):
            raise ValueError("encoders_over_time needs no random walk (process_std_rel 0)")
        return cls(noise, update_every, compensate, over_time, rollback)

    def modes(self, fusion, params, inst, peers, cov, own=None):
        """(this update's own modes (E, dY) at ``params`` (``own_modes``), its R ``cov``,
        ``params``), or None where the motion noise has no modes; ``own`` E where the motion
        noise's call has already made it (``instant_terms``). ``peers()`` gives the peers'
        [(T_j, message_j)], asked for only where the modes are made here."""
        slope = self.compensation is not None  # dY: the compensation's alone
        if own is not None and not slope:
            return (own, None), cov, params
        args = (inst.motion_jac, inst.regressor, peers())
        modes = own_modes(self.noise, fusion, params, *args, slope=slope, known=own)
        return None if modes is None else (modes, cov, params)

    def add(self, stamp: int, measurement: tuple, update: tuple, cov_before, walk) -> None:
        """Take in a used update (``measurement`` (z, Y, b, R), ``update`` of ``modes``; P
        before it and the walk Q, for the compensation's discount)."""
        if self.compensation is not None:
            self.compensation.add_update(self.noise, update, cov_before, walk)
        if self.encoder_cov is not None:
            index = stamp // self.update_every
            self.encoder_cov.add(index, measurement[1], measurement[3], update[0][0])

    def offset(self, ukf) -> np.ndarray | None:
        """The compensation's d for the filter's (x, P) (None without it)."""
        return None if self.compensation is None else self.compensation.offset(ukf.x, ukf.P)

    def covariance(self, cov: np.ndarray) -> np.ndarray:
        """The reported covariance for the filter's P ``cov``."""
        return cov if self.encoder_cov is None else self.encoder_cov.covariance(cov)

    def std(self, cov: np.ndarray, out: np.ndarray) -> None:
        """sqrt(diag(``covariance(cov)``)) into ``out`` (10,), without the full product."""
        if self.encoder_cov is None:
            np.sqrt(cov.diagonal(), out=out)
        else:
            self.encoder_cov.std(cov, out)

    def state(self) -> tuple:
        """The reports' states, for ``restore`` on a rollback (their arrays shared: the
        reports replace them, never change them in place)."""
        return tuple([r.state() for r in self._reports])

    def restore(self, state: tuple) -> None:
        for report, saved in zip(self._reports, state, strict=True):
            report.restore(saved)
