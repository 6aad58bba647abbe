"""With ideal sensors the estimator converges to the truth whatever the arms do within their
servo limits (issue 15, item 1).

The hardest motion the servos allow: both joints driven at their 0.12 rad/s rate limit, the
requested target flipping every half period (a triangle wave of the servo targets, tilt and pan in
quadrature), thrusters idle, so the only excitation is the arm's reaction. Before the fix the
estimator's filter read the IMU's and the thrust's period means as point samples at the end of
the period, dt/2 later than the encoders' samples, and the balance kept dt/2 times the rate of
change of the arm's momentum rate: 8-20 % mass error and most updates gated. That is fixed (the
means enter the filter with a zero-order hold): no update is gated and the mass is within 1 %.

What remains is the issue's bound itself (mass 0.1 %, principal moments 1 %), kept here as a
strict expected failure: the balance is nonlinear in the pre-filtered signals (rotations by the
joint angles, products of rates) and the 1 Hz pre-filter distorts the harmonics of the servo-driven
motion before the products (the filter departs from a pure delay by 3/2 (f / f_w)^2). Measured
with exact MuJoCo kinematics through the same filters at a 3 s period, the second principal
moment is off by 22.5, 6.1, 1.6, 0.44 % at pre-filter cutoffs of 1, 2, 4, 8 Hz; a faster
pre-filter is not the cure (at 4 Hz the encoder noise, doubly differentiated and squared in the
velocity products, biased the nominal tumble's centre of mass by 2 mm).
"""

import numpy as np
import pytest

from astrocargo.envs.transport import ARM_SPEED_RADPS, CargoTransport
from astrocargo.estimator.preprocess import StateVariableFilter

PERIOD_S = 6.0  # the worst case (16-21 % mass error before the fix)
DURATION_S = 90.0
# The bound (must-show of issue 15 item 1).
MASS_TOL = 1e-3  # relative
COM_TOL_M = 5e-4
PRINCIPAL_TOL = 1e-2  # relative, each principal moment
# What the timing fix alone reaches (main: 40 % mass error, most updates gated).
FIXED_MASS_TOL = 1e-2
FIXED_COM_TOL_M = 1e-3


def _arm_oscillation(t_s: float, n_robots: int) -> np.ndarray:
    """Thrust idle; each arm's requested targets flip every half period (tilt and pan a quarter
    period apart, robots in opposition): the servo targets move at the rate limit throughout."""
    actions = np.zeros((n_robots, 8))
    for i in range(n_robots):
        phase = 2 * np.pi * t_s / PERIOD_S + i * np.pi
        actions[i, 6] = np.sign(np.sin(phase))
        actions[i, 7] = np.sign(np.cos(phase))
    return actions


@pytest.fixture(scope="module")
def arm_run():
    sim = CargoTransport(n_robots=1, trajectory="hover", noise="ideal", observe_estimates=False)
    sim.reset(np.random.default_rng(0))
    targets = [sim.arm_targets.copy()]
    for k in range(1, int(round(DURATION_S / sim.dt_s)) + 1):
        result = sim.step(_arm_oscillation(k * sim.dt_s, sim.n_robots))
        assert not result.terminated, result.termination_reason
        targets.append(sim.arm_targets.copy())
    return sim, np.array(targets), result.infos[0]


def test_arm_moves_at_the_servo_rate_limit(arm_run):
    sim, targets, _ = arm_run
    speed = np.abs(np.diff(targets, axis=0)) / sim.dt_s
    # The targets move at the limit nearly all the time (a triangle wave), never faster.
    assert speed.max() <= ARM_SPEED_RADPS * (1 + 1e-9)
    assert np.mean(speed > 0.99 * ARM_SPEED_RADPS) > 0.95


def test_ideal_sensors_no_timing_bias_under_fastest_arm_motion(arm_run):
    sim, _, info = arm_run
    counters = info["estimator"]
    assert counters["gated"] == 0, counters
    assert counters["updates"] > 0.9 * (DURATION_S - 5.0) * sim.control_hz / 10, counters
    assert info["mass_rel_err"] <= FIXED_MASS_TOL, info["mass_rel_err"]
    assert info["com_err_m"] <= FIXED_COM_TOL_M, info["com_err_m"]


@pytest.mark.xfail(
    strict=True,
    reason="pre-filter distortion before the balance's products (module docstring): "
    "measured mass 0.78 %, CoM 0.52 mm, principal moments 1.5 / 6.5 / 0.20 % at this motion",
)
def test_ideal_sensors_converge_under_fastest_arm_motion(arm_run):
    _, _, info = arm_run
    assert info["mass_rel_err"] <= MASS_TOL, info["mass_rel_err"]
    assert info["com_err_m"] <= COM_TOL_M, info["com_err_m"]
    assert max(info["principal_rel_err"]) <= PRINCIPAL_TOL, info["principal_rel_err"]


@pytest.mark.parametrize("held", [True, False])
def test_period_means_are_held_not_points(held):
    """A signal's period means and the point samples of its second integral must give the same
    filtered signal: q(t) = sin(w t) sampled at t_k, and qdd's mean over each period
    (qd(t_k) - qd(t_k-1)) / dt, as the IMU reports it. Held (zero-order hold of the new sample
    over the period it describes) they agree to O((w dt)^2); as point samples the mean lags by
    dt/2, an error of w dt / 2 relative, which the check must see."""
    dt, w = 0.016, 2 * np.pi * 0.5
    filt = StateVariableFilter(2, dt, 1.0, held=[1] if held else None)
    t = np.arange(2000) * dt
    q, qd = np.sin(w * t), w * np.cos(w * t)
    qdd_mean = np.concatenate(([0.0], np.diff(qd) / dt))
    qdd_mean[0] = qdd_mean[1]
    out = []
    for u in zip(q, qdd_mean, strict=True):
        y, _, ydd = filt.step(np.array(u))
        out.append((ydd[0], y[1]))
    out = np.array(out)[500:]
    rel = np.max(np.abs(out[:, 0] - out[:, 1])) / np.max(np.abs(out[:, 0]))
    if held:
        assert rel < 0.2 * (w * dt) ** 2
    else:
        assert rel > 0.3 * w * dt
