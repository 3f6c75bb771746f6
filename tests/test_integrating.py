"""The measurement of the agent on integrating processes (service.learn.integrating):
its reference tuning against the closed form, its scoring, and the check that pauses
every one of its integrators through the engine."""

from __future__ import annotations

import numpy as np
import pytest

from service.learn import integrating

pytestmark = pytest.mark.timeout(300)


def test_the_reference_is_simc_for_integrating_processes():
    """Skogestad 2003 for k'/s e^(-theta s): Kc = 1/(k' (tau_c + theta)), tau_I =
    4 (tau_c + theta); the lag standing for the integrator changes nothing."""
    slope, theta = integrating.plants()
    kp, ki = integrating.simc_gains(slope, theta)
    tc = integrating.TAU_CL + theta
    np.testing.assert_allclose(kp, 1.0 / (slope * tc), rtol=1e-9)
    np.testing.assert_allclose(ki, kp / (4.0 * tc), rtol=1e-9)


def test_the_score_tells_a_slow_oscillation_from_an_unstable_loop():
    slope, theta = np.array([1.0, 1.0, 1.0]), np.array([0.05, 0.05, 0.5])
    kp, ki = integrating.simc_gains(slope, theta)
    # SIMC's tuning; the paper's start (damping 0.11, a period of 28 time units); far too
    # much gain for a dead time of 0.5 (kp = 20: the ultimate gain is pi / (2 * 0.5))
    kp = np.array([kp[0], 0.05, 20.0])
    ki = np.array([ki[0], 0.05, 1.0])
    mse, unsettled, unstable = integrating.scores(slope, theta, kp, ki)
    assert mse[0] < 0.06 and not unsettled[0] and not unstable[0]
    assert unsettled[1] and not unstable[1] and mse[1] > 10 * mse[0]
    assert unstable[2]


def test_the_check_pauses_every_integrator_through_the_engine():
    """The default guard (the hint checked): each of the nine integrators is paused as
    integrating at the first assessment with two events, and the agent takes no step
    after (verification may still judge its last change, and roll it back)."""
    from service.agent.model import load_agent

    slope, theta = integrating.plants()
    done = integrating.run(load_agent(), integrating.CONDITIONS[0], None, periods=16)
    # checked() drains the audit rows: read them first, then hand them back
    gains_rows, audit = done.engine.drain_changes()
    done.engine.requeue(gains_rows, audit)
    result = integrating.checked(done, slope, theta)
    paused = result["paused_at_s"]
    assert all(t is not None and t <= 14 * integrating.PERIOD_S for t in paused), result
    assert set(result["status"]) == {"out_of_envelope"}
    steps = [(int(r[0][1:]), r[2]) for r in audit if r[5] == "agent"]
    assert steps and all(t < paused[i] for i, t in steps)
