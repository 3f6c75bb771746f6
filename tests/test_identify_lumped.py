"""Lumped models (identify.LUMP_THETA): loops whose setpoint only ramps slower than the
loop, through the engine (docs/identification.md, Lumped models)."""

from __future__ import annotations

import orjson
import pytest

from service.agent import untrained_agent
from service.engine import TuningEngine
from service.engine.identify import LUMP_EVENTS, LUMP_THETA, MIN_SNR
from tests.test_identify import TAU, THETA, K, drive, hint_free, hinted


def test_a_ramp_slower_than_the_loop_gives_a_lumped_model_and_its_tuning():
    """Ramps over 3 tau (slower than tau + theta) show K and the lag tau + theta, not the
    split (identify.RAMP_SHOWN): the model put in force is lumped, K and the lag within
    10 %, theta identify.LUMP_THETA of the lag, and the loop is tuned from it."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    updates = drive(engine, moves=6, ramp=3.0)
    view = engine.view("L", wall=float(10**4))
    m = view.identification.in_force
    assert view.counters.identified == 1 and m is not None and m.lumped and m.confident
    assert m.k == pytest.approx(K, rel=0.1)
    assert m.tau + m.theta == pytest.approx(TAU + THETA, rel=0.1)
    assert m.theta == pytest.approx(LUMP_THETA * (m.tau + m.theta))
    assert all(ev.ramp_s > TAU + THETA for ev in view.identification.events if ev.move)
    assert updates and updates[0].reason == "model"


def test_a_lumped_model_in_force_gives_way_to_the_split_that_steps_show():
    """Five ramps over 3 tau put a lumped model in force; the setpoint steps after them
    show tau and theta apart, and that model replaces it (model_check.refined: the
    lumped tuning predicted worse than guard.model_check times the split model's), its
    tuning put in force (``followed``)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=12, ramp=[3.0] * 5 + [0.0], every=6.0)
    ident = engine.view("L", wall=1e5).identification
    assert not ident.in_force.lumped
    assert ident.in_force.tau == pytest.approx(TAU, rel=0.1)
    assert ident.in_force.theta == pytest.approx(THETA, abs=0.3 * THETA)
    _, audit = engine.drain_changes()
    rows = [(r[5], orjson.loads(r[-1])) for r in audit if r[5] in ("identified", "model")]
    assert [reason for reason, _ in rows] == ["identified", "model", "model"]
    assert rows[0][1]["lumped"] and rows[2][1]["after"] == "followed"


@pytest.mark.parametrize(("tau_factor", "flagged"), [(1.0, False), (3.0, True), (1 / 3, False)])
def test_a_lumped_model_flags_a_hint_slower_than_its_lag_only(tau_factor, flagged):
    """A hinted loop whose setpoint only ramps slower than the loop: its lumped model
    (K, the lag 50 s) confirms the true hint, flags one 3x too slow (120 s > 2x the whole
    lag), and cannot tell one 3x too fast (13 s) from a longer dead time: not flagged."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(tau_hat=TAU * tau_factor), wall=0.0)
    drive(engine, moves=6, ramp=3.0, every=6.0)
    view = engine.view("L", wall=1e5)
    assert view.identification.model.lumped and view.identification.model.confident
    assert view.identification.mismatch == flagged
    assert view.counters.mismatches == int(flagged)


def test_a_lumped_attempt_that_fails_is_reported_as_none_was_made():
    """Ramps over 3 tau under 4x the noise: three of the four stand out of it (a lumped
    attempt, identify.LUMP_EVENTS), too noisy for a confident K and lag. The assessment
    then shows what the strict rule saw: no event excited, a model not lumped, counting
    none, and the ramps' verdict."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=4, ramp=3.0, noise=4.0)
    ident = engine.view("L", wall=1e5).identification
    assert sum(ev.snr >= MIN_SNR for ev in ident.events) >= LUMP_EVENTS  # attempted
    assert not any(ev.excited for ev in ident.events)
    m = ident.model
    assert not m.lumped and not m.confident and m.events == 0
    assert "slower than the loop" in ident.why and ident.in_force is None
