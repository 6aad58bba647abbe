"""One control period of MuJoCo for the env: ``frame_skip`` calls of ``mj_step``, then the
stages of ``mj_forward`` that the step reads (positions, contacts and position sensors, then
velocities), with no work done twice.

``mj_step`` starts with ``mj_forward`` of the state it is given; the position and velocity
stages of that state are what the previous period ended with. While qpos and qvel are exactly as
that period (or ``mj_forward`` at reset) left them, and the integrator is RK4 (the MJCF's), the
first ``mj_step`` is run as its parts without those two stages: ``mj_sensorVel``,
``mj_forwardSkip`` from the acceleration stage, ``mj_checkAcc`` and ``mj_RungeKutta`` (the same
numbers, bit for bit, with one position stage less). Its ``mj_checkPos`` and ``mj_checkVel`` are
left out too: they act only on an entry that is NaN or beyond ``mjMAXVAL`` in magnitude, and the
state is taken as unchanged only when it has none. A state changed from outside (anything
writing qpos or qvel between steps), or one such entry, is noticed and stepped in full. The
model must not change between steps except through a reset.

After the period the acceleration stage (qacc, constraint forces, acceleration sensors) stays as
``mj_step`` computed it, for the state before its last integration: nothing the step reads uses
it, and the next ``mj_step`` recomputes it.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import (
    mj_checkAcc,
    mj_forwardSkip,
    mj_fwdPosition,
    mj_fwdVelocity,
    mj_RungeKutta,
    mj_sensorPos,
    mj_sensorVel,
    mj_step,
)
from numba import njit

from astrocargo.estimator.checks import all_finite

# MuJoCo's instability warnings: on a bad qpos, qvel or qacc it resets the state to the model's
# initial one (and counts the warning), so after one the physics no longer continues.
UNSTABLE_WARNINGS = np.array(
    [int(getattr(mujoco.mjtWarning, f"mjWARN_BAD{x}")) for x in ("QPOS", "QVEL", "QACC")]
)
_STAGE_VEL = int(mujoco.mjtStage.mjSTAGE_VEL)
MAX_VALUE = float(mujoco.mjMAXVAL)  # mj_checkPos, mj_checkVel: beyond it an entry is bad


@njit(cache=True)
def state_finite(qpos, qvel, warnings, unstable, saved_qpos, saved_qvel):
    """Whether the physics state is finite and MuJoCo counted none of the ``unstable``
    warnings; the state is copied to ``saved_qpos``, ``saved_qvel`` (what the next period's
    check compares against)."""
    saved_qpos[:] = qpos
    saved_qvel[:] = qvel
    for w in unstable:
        if warnings[w] > 0:
            return False
    return all_finite(qpos) and all_finite(qvel)


@njit(cache=True)
def same_state(qpos, qvel, saved_qpos, saved_qvel):
    """Whether qpos and qvel are still those saved (NaN counts as changed) with every entry
    within +-``MAX_VALUE`` (where ``mj_checkPos`` and ``mj_checkVel`` leave the state alone);
    compared entry by entry (``np.array_equal`` builds temporaries)."""
    return _same_within_bound(qpos, saved_qpos) and _same_within_bound(qvel, saved_qvel)


@njit(cache=True, inline="always")
def _same_within_bound(values, saved):
    """``same_state`` of one array and its saved copy."""
    if values.shape[0] != saved.shape[0]:
        return False
    for k in range(values.shape[0]):
        if not values[k] == saved[k] or abs(values[k]) > MAX_VALUE:
            return False
    return True


class PeriodStepper:
    """Steps ``data`` of ``model`` one control period at a time (module docstring)."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, frame_skip: int) -> None:
        self.model, self.data, self.frame_skip = model, data, frame_skip
        opt = model.opt
        fwdinv = opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_FWDINV)
        self.skip_allowed = opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 and not fwdinv
        self.bind_views()
        self.saved_qpos, self.saved_qvel = np.full(model.nq, np.nan), np.full(model.nv, np.nan)

    def bind_views(self) -> None:
        """Views of the data's arrays (each property access builds a new one)."""
        data = self.data
        self.qpos, self.qvel, self.warnings = data.qpos, data.qvel, data.warning.number

    # A copy (copy.deepcopy, pickle) steps its first period in full.
    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("qpos", "qvel", "warnings")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.bind_views()
        self.saved_qpos[:] = np.nan

    def forward_done(self) -> None:
        """The data's position and velocity stages are those of its qpos and qvel now (after
        ``mj_forward``)."""
        self.saved_qpos[:] = self.qpos
        self.saved_qvel[:] = self.qvel

    def unchanged(self) -> bool:
        """Whether qpos and qvel are as the last period (or ``forward_done``) left them, with
        no entry that ``mj_checkPos`` or ``mj_checkVel`` would act on (``same_state``)."""
        return same_state(self.qpos, self.qvel, self.saved_qpos, self.saved_qvel)

    def advance(self, unchanged: bool) -> bool:
        """One period (``unchanged``: ``self.unchanged()`` at its start); returns whether the
        state is finite and stable."""
        self.integrate(unchanged)
        return state_finite(
            self.qpos, self.qvel, self.warnings, UNSTABLE_WARNINGS, self.saved_qpos,
            self.saved_qvel,
        )  # fmt: skip

    def integrate(self, unchanged: bool) -> None:
        """``advance`` without its check of the state: the caller runs ``state_finite`` (with
        ``saved_qpos`` and ``saved_qvel``) before the next period."""
        m, d = self.model, self.data
        n_step = self.frame_skip
        if self.skip_allowed and unchanged:
            mj_sensorVel(m, d)
            mj_forwardSkip(m, d, _STAGE_VEL, 0)
            mj_checkAcc(m, d)
            mj_RungeKutta(m, d, 4)
            n_step -= 1
        if n_step:
            mj_step(m, d, nstep=n_step)
        mj_fwdPosition(m, d)
        mj_sensorPos(m, d)
        mj_fwdVelocity(m, d)
