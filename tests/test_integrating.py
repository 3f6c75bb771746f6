"""Integrating processes: identification reports them (and pauses a hinted one), and
the measurement of the agent on them (service.learn.integrating): its reference tuning
against the closed form, its scoring, and the check that pauses every one of its
integrators through the engine."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine
from service.learn import integrating
from service.wire.protocol import LoopStatus
from tests.test_identify import H, K, drive, gains

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
    # much gain for a dead time of 0.5
    kp = np.array([kp[0], 0.05, 20.0])
    ki = np.array([ki[0], 0.05, 1.0])
    mse, unsettled, unstable = integrating.scores(slope, theta, kp, ki)
    assert mse[0] < 0.06 and not unsettled[0] and not unstable[0]
    assert unsettled[1] and not unstable[1] and mse[1] > 10 * mse[0]
    assert unstable[2]


def test_the_phase_margin_matches_a_long_simulation():
    """kp 2, ki 0.5 on 1/s: crossover at w = 2.015, atan(8.06) = 1.447 rad of phase lead,
    so stable below a dead time of 0.718 and unstable above: 40 time units of the step
    test (dt 0.01) decay at 0.6 and grow at 0.85."""
    from plant_sim.loop import step_test

    theta = np.array([0.6, 0.85])
    margin = integrating.phase_margin(1.0, theta, 2.0, 0.5)
    np.testing.assert_allclose(margin, np.arctan(2.0 * 2.0153 / 0.5) - 2.0153 * theta, atol=1e-3)
    assert margin[0] > 0 > margin[1]
    trace = step_test(integrating.LAG, integrating.LAG, theta, 2.0, 0.5, horizon=40.0)
    err = np.abs(trace.y - 1.0)
    early, late = err[:, 1000:2000].max(axis=1), err[:, -1000:].max(axis=1)
    assert late[0] < 0.1 * early[0] and late[1] > early[1]


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


@pytest.mark.parametrize("noise", [0.2, 0.0])
def test_an_integrating_loop_is_reported_as_such_and_never_identified_as_foptd(noise):
    """Also without noise (a simulated level, a smooth transmitter), where the
    integrating model's residual is sharp in the dead time: taken at the grid's and the
    FOPTD's dead times alone it was 5x the FOPTD's, and the loop said "K or tau not
    pinned down" (foptd_fit._integrating_fit)."""
    engine = TuningEngine(untrained_agent(0))
    kp, ki = 0.05, 0.0002
    engine.register(LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H), wall=0.0)
    drive(engine, k=0.01, moves=6, integrating=True, every=8.0, size=10.0, noise=noise)
    view = engine.view("L", wall=1e9)
    assert view.counters.identified == 0
    assert view.identification.why.startswith("integrating"), view.identification.why
    # the view carries the integrator's own numbers (drive's: k = 0.01 per second)
    model = view.identification.model
    assert model.integrating and model.slope == pytest.approx(0.01, rel=0.05)
    if not noise:  # as in the hinted case below
        assert model.theta_i == pytest.approx(2 * H, abs=0.1 * H)


@pytest.mark.parametrize("noise", [0.2, 0.0])
def test_a_hinted_loop_on_an_integrating_process_is_paused_with_its_model(noise):
    """A loop registered with an FOPTD hint whose process integrates (a level): the
    check pauses it (status out_of_envelope, the alarm's counter, an audit row with the
    integrator's K and dead time) and the agent, which does not tune integrators
    (service.learn.integrating: 7-18x SIMC's step-test MSE), takes no step after.
    Before, an integrating verdict paused nothing: the agent went on tuning it."""
    engine = TuningEngine(untrained_agent(0))
    scaling = {"k_hat": 2.0, "tau_hat": 200.0, "pv_scale": 10.0}
    engine.register(
        LoopConfig(id="L", kp=0.05, ki=0.0002, sample_period_s=H, scaling=scaling,
                   guard={"identify": True}),
        wall=0.0,
    )  # fmt: skip
    drive(engine, k=0.01, moves=6, integrating=True, every=8.0, size=10.0, noise=noise)
    view = engine.view("L", wall=1.0)
    assert view.status == LoopStatus.out_of_envelope
    assert view.counters.envelope_pauses == 1 and view.identification.out_of_envelope
    assert view.identification.why.startswith("integrating"), view.identification.why
    _, audit = engine.drain_changes()
    (row,) = [r for r in audit if r[5] == "out_of_envelope"]
    detail = json.loads(row[10])
    assert detail["integrating"] is True
    why = view.status_why  # the K of the integrator that paused it, and the next step
    k_per_s = float(re.match(r"the process looks integrating \(K = ([0-9.e-]+) PV units", why)[1])
    assert k_per_s == pytest.approx(detail["k_per_s"], rel=5e-3) and "PATCH mode frozen" in why
    assert f"identified at t = {row[2]:.10g} s, plant time" in why
    # drive's integrator: d pv / dt = k u (k = 0.01 per second), dead time THETA
    assert detail["k_per_s"] == pytest.approx(0.01, rel=0.05)
    if not noise:  # (under noise these slow ramps, 0.02 a sample, hide the onset)
        # the simulation's 2.5-sample dead time acts on these data as 2 samples exactly
        # (the integrating model's residual there: 1e-13)
        assert detail["theta_s"] == pytest.approx(2 * H, abs=0.1 * H)
    paused_at = row[2]
    later = drive(engine, k=0.01, moves=3, integrating=True, every=8.0, size=10.0,
                  noise=noise, t0=paused_at + 1e4)  # fmt: skip
    assert later == [] and engine.view("L", wall=1.0).counters.envelope_pauses == 1


def test_a_slow_lag_in_the_box_that_fits_an_integrator_as_well_is_not_paused():
    """Setpoint moves every 0.15 tau: a segment far shorter than the lag fits an
    integrator as well as the FOPTD (the verdict says integrating), but the FOPTD's lag,
    seen through the hint, is in the agent's box: the agent tunes it, unpaused (an
    integrating verdict pauses only with its FOPTD out of the envelope)."""
    engine = TuningEngine(untrained_agent(0))
    kp, ki = gains(tau=400.0)
    scaling = {"k_hat": K, "tau_hat": 400.0, "pv_scale": 20.0}
    engine.register(
        LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H, scaling=scaling,
                   guard={"identify": True}),
        wall=0.0,
    )  # fmt: skip
    drive(engine, tau=400.0, theta=40.0, moves=12, every=0.15, noise=0.1)
    view = engine.view("L", wall=1.0)
    assert view.identification.why.startswith("integrating"), view.identification.why
    assert view.status == LoopStatus.tuning and view.counters.envelope_pauses == 0


def test_the_command_stands_alone_and_its_report_renders_from_its_json(tmp_path, capsys):
    """``pitune evaluate --integrating`` refuses --robust before anything runs; the
    shipped report is its JSON rendered (a None score, an unstable loop's, included)."""
    from pathlib import Path

    from service.cli import main

    out = tmp_path / "x"
    assert main(["evaluate", "--integrating", "--robust", "--out", str(out)]) == 2
    assert "a measurement of its own" in capsys.readouterr().err
    assert not out.exists()
    reports = Path(__file__).resolve().parents[1] / "reports"
    result = json.loads((reports / "integrating.json").read_text())
    assert integrating.render(result) == (reports / "integrating.md").read_text()
    result["agent"][0]["mse"][0] = result["agent"][0]["ratio_to_simc"][0] = None
    assert "| paper protocol | " in integrating.render(integrating._finite(result))
