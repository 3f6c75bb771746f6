"""Identification from an operator's bump tests (service.engine.watch.record): a loop in
manual whose samples carry the output ``op`` is open-loop data, and each step of the
output opens an event as a setpoint move does in auto. A loop that only regulates (no
setpoint moves: load disturbances alone do not identify it, docs/identification.md)
is identified from two or three steps of its output."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from service.agent import untrained_agent
from service.engine import TuningEngine
from service.engine.identify import LUMP_THETA
from service.wire.protocol import LoopStatus
from tests.test_identify import TAU, THETA, H, K, hint_free

pytestmark = pytest.mark.timeout(120)


def bumps(
    engine, *, steps=4, every=5.0, size=4.0, noise=0.5, track=True, op=True, op_noise=0.0,
    back=0, ramp=1,
):  # fmt: skip
    """The loop in manual at 25 % output, its output stepped by +-``size`` every ``every``
    time constants; ``track``: the DCS's setpoint tracks the PV in manual (else it stays
    at the last one in auto); ``op``: the samples carry the output, with white noise of
    ``op_noise`` (a valve's position feedback); then ``back`` samples in auto, the
    setpoint left where tracking put it, the output held; each step made over ``ramp``
    samples. Returns the gain updates published."""
    rng = np.random.default_rng(2)
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=noise, seed=1,
                       max_theta=THETA / H)  # fmt: skip
    u = 25.0
    plant.reset(K * u)
    per = int(round(every * TAU / H))
    manual = (steps + 1) * per
    updates, sp = [], K * 25.0
    for j in range(manual + back):
        if j >= per and j % per < ramp and j < manual:
            u += (size if (j // per) % 2 else -size) / ramp
        y = float(plant.measure()[0])
        if track and j <= manual:
            sp = y
        sample = {"loop_id": "L", "t": j * H, "sp": sp, "pv": y, "auto": j >= manual}
        if op:
            sample["op"] = u + op_noise * float(rng.standard_normal())
        updates += engine.ingest([sample], wall=float(j))
        plant.step(np.array([u]))
    return updates


@pytest.mark.parametrize(("track", "op_noise"), [(True, 0.0), (False, 0.0), (True, 0.075)])
def test_a_loop_in_manual_is_identified_from_steps_of_its_output(track, op_noise):
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    updates = bumps(engine, track=track, op_noise=op_noise)
    view = engine.view("L", wall=250.0)  # (the last sample's)
    ident = view.identification
    assert view.counters.identified == 1, ident.why
    m = ident.in_force
    assert m.k == pytest.approx(K, rel=0.05)
    assert m.tau == pytest.approx(TAU, rel=0.1)
    assert m.theta == pytest.approx(THETA, abs=0.2 * THETA)
    # the events are the output's steps; the typical move is the PV change they make
    steps = [ev.op_move for ev in ident.events]
    assert len(steps) >= 2 and all(abs(x) == pytest.approx(4.0, abs=0.2) for x in steps), steps
    assert all(ev.move == 0.0 for ev in ident.events)
    assert m.move == pytest.approx(4.0 * K, rel=0.1)
    # its tuning is published, ready for auto (the DCS holds it while in manual)
    assert updates and view.scaling is not None
    assert view.status == LoopStatus.manual


def test_without_op_in_the_samples_a_loop_in_manual_says_why_and_stays_identifying():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    assert bumps(engine, op=False) == []
    view = engine.view("L", wall=1e6)
    assert view.counters.identified == 0 and view.scaling is None
    assert "manual, without op" in view.identification.why, view.identification.why


def test_an_output_that_only_wanders_in_manual_opens_no_event():
    """Noise on the output (a valve's position feedback, 0.3 % of it rms here) is no
    operator's step (watch.MANUAL_STEP): no event, no model."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    assert bumps(engine, size=0.0, op_noise=0.075) == []
    view = engine.view("L", wall=250.0)
    assert view.identification.events == [] and view.identification.model is None
    assert "output step in manual" in view.identification.why, view.identification.why


@pytest.mark.parametrize("ramp", [3, 30])
def test_an_output_ramped_slower_than_the_loop_yields_a_lumped_model(ramp):
    """An operator holding a raise/lower button: each step of 24 (on an output of 25) made
    over ``ramp`` samples, every sample's change a step (above watch.MANUAL_STEP). Over 3
    samples (a third of tau) the steps identify the loop; over 30 (3 tau, slower than
    tau + theta) the data need not tell tau from the dead time (the rule of setpoint ramps,
    identify.RAMP_SHOWN; on the bar's loops ramped over 30 samples 1 of 7 models was 43 %
    off in tau before it: tests.identify_bumps --ramp 30), only K and the lag tau +
    theta: the model is lumped (identify.LUMP_THETA), and says so."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    bumps(engine, size=24.0, every=8.0, ramp=ramp)
    ident = engine.view("L", wall=1e6).identification
    assert ident.in_force is not None, ident.why
    assert ident.in_force.lumped == (ramp == 30)
    assert ident.in_force.k == pytest.approx(K, rel=0.1)
    if ramp == 3:
        assert ident.in_force.tau == pytest.approx(TAU, rel=0.15)
    else:
        lag = ident.in_force.tau + ident.in_force.theta
        assert lag == pytest.approx(TAU + THETA, rel=0.1)
        assert ident.in_force.theta == pytest.approx(LUMP_THETA * lag)


def test_bump_tests_identify_the_bars_loops():
    """Issue 13's bar loops (K 0.01-10, tau 5-2,000 s, theta/tau 0-1, 5-50 samples per
    tau, noise 1 % of span) in manual, their outputs stepped every 3-6 tau
    (tests.identify_bumps; 60 loops of seeds 0 and 1: all identified from their first 3
    steps, K and tau within 13 % and 19 %): the first 12 of seed 0."""
    from tests.identify_bar import Plants
    from tests.identify_bumps import run

    result = run(Plants.random(12, 0), steps=3, seed=1)
    assert result["identified_from_first"][3] == 12, result
    assert result["k_and_tau_within_30pct"] == 12, result
    errors = result["abs_err_p50_p90_max"]  # (measured: worst 5.3 % and 15.6 %)
    assert errors["k"][2] < 0.1 and errors["tau"][2] < 0.2, result


def test_back_in_auto_the_segment_goes_on_and_a_tracked_setpoint_is_no_move():
    """The loop back in auto from a bump test: the plant is the same, so the segment goes
    on; the setpoint the DCS tracked to the PV differs from the one recorded in manual,
    but nothing stepped: no event (the same run without the return to compare)."""
    starts = []
    for back in (0, 20):
        engine = TuningEngine(untrained_agent(0))
        engine.register(hint_free(), wall=0.0)
        bumps(engine, steps=4, back=back)
        tb, s = engine.table, engine.table.slot("L")
        assert tb.rec[s] >= 0
        starts.append(list(tb.ident[s].starts))
    assert len(starts[0]) >= 2 and starts[1] == starts[0]


def test_a_manual_stretch_not_recorded_still_ends_the_segment():
    """A loop whose samples carry no op: a stretch in manual whose samples carry only the
    error (not recorded) ends the segment when the loop is back in auto, as any stretch
    in manual does (its output is unknown)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    tb, s = engine.table, engine.table.slot("L")
    for j, sp in enumerate([50.0, 60.0, 60.0]):
        engine.ingest([{"loop_id": "L", "t": j * H, "sp": sp, "pv": 50.0}], wall=j)
    assert tb.rec[s] >= 0  # a segment opened at the move
    for j in (3, 4):
        engine.ingest([{"loop_id": "L", "t": j * H, "e": 9.0, "auto": False}], wall=j)
    engine.ingest([{"loop_id": "L", "t": 5 * H, "sp": 60.0, "pv": 51.0}], wall=5)
    assert tb.rec[s] == -1
    assert engine.view("L", wall=5).identification.why.startswith("segment ended: data gap")
