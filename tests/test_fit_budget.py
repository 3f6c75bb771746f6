"""The identification budget (service.engine.fit_budget): the model fits take at most a
share of a core; assessments beyond it are owed and made in turn as the budget refills,
loops without a model first; the REST view and the tuner's metrics say so."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest

from service.agent import untrained_agent
from service.engine import SiteDefaults, TuningEngine, fit_budget, identify
from service.engine.fit_budget import PASS_S, WINDOW_S, FitBudget
from tests.test_identify import TAU, THETA, H, K, drive, gains, hint_free, hinted

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def dear_fits(monkeypatch):
    """Every fit charged 1.5 pass budgets of CPU: the engine tests below need one fit to
    overdraw a pass (PASS_S) as on a busy box (5-30 ms a fit), which an idle one no longer
    does (under 10 ms), so the budget's own clock is made deterministic."""
    ticks = itertools.count(0.0, 1.5 * PASS_S)  # timed() reads it before and after a fit
    monkeypatch.setattr(fit_budget, "time", SimpleNamespace(thread_time=lambda: next(ticks)))


def test_the_bucket_refills_with_the_wall_clock_caps_at_its_window_and_limits_a_pass():
    fits = FitBudget(0.1)
    cap = 0.1 * WINDOW_S
    assert fits.cap == pytest.approx(cap) and fits.tokens == pytest.approx(cap)
    fits.refill(0.0)
    assert fits.allows()
    fits.timed(sum, range(10**6))  # a few ms of CPU, charged to the bucket and the pass
    assert fits.spent_s > 0.0 and fits.tokens == pytest.approx(cap - fits.spent_s)
    fits.pass_left = 0.0  # the pass spent its share: the next assessment is owed
    assert not fits.allows()
    fits.refill(0.0)  # a new pass
    assert fits.allows()
    fits.tokens = -0.05  # as after fits dearer than the bucket
    assert not fits.allows()
    fits.refill(0.4)  # 0.4 s x 0.1 = 0.04: still in debt
    assert not fits.allows() and fits.tokens == pytest.approx(-0.01)
    fits.owe(1, urgent=True)
    assert fits.wait_s(0.4) == pytest.approx(0.1) and fits.wait_s(0.45) == pytest.approx(0.05)
    fits.refill(1000.0)
    assert fits.tokens == pytest.approx(cap) and fits.wait_s(1000.0) == 0.0
    fits.refill(10.0)  # a wall clock going back refills nothing
    assert fits.tokens == pytest.approx(cap)
    unlimited = FitBudget(None)
    unlimited.tokens, unlimited.pass_left = -1.0, -1.0
    assert unlimited.allows() and unlimited.wait_s(0.0) is None


def test_owed_loops_come_in_turn_loops_without_a_model_first():
    fits = FitBudget(0.1)
    fits.owe(3, urgent=False)
    fits.owe(7, urgent=True)
    fits.owe(3, urgent=False)  # owed once
    fits.owe(5, urgent=False)
    fits.owe(9, urgent=True)
    assert fits.waiting == 4 and fits.deferred == 4
    fits.forget(5)
    assert [fits.next_owed() for _ in range(4)] == [7, 9, 3, None]
    assert fits.waiting == 0


def test_a_spent_budget_owes_the_assessment_and_makes_it_when_it_refills(dear_fits):
    """With a budget far below one fit per run (1e-6 of a core: after the first fit the
    bucket is in debt for hours of wall time) a hint-free loop is assessed once and then
    owed: it stays identifying, says why, and publishes nothing; once the wall clock has
    refilled the bucket, the engine's catch-up (the tuner's, between messages) assesses
    it on its latest data (six moves): it is identified and its first tuning is
    returned. The unlimited engine identifies it during the run."""
    free = TuningEngine(untrained_agent(0))
    free.register(hint_free(), wall=0.0)
    drive(free, moves=6)
    assert free.view("L", wall=1e9).identification.state == "checking"  # identified

    engine = TuningEngine(untrained_agent(0), site=SiteDefaults(fit_share=1e-6))
    engine.register(hint_free(), wall=0.0)
    assert drive(engine, moves=6) == []
    view = engine.view("L", wall=1e9)
    assert view.identification.state == "identifying"
    assert "waiting for the identification budget" in view.identification.why
    fits = engine.table.fits
    assert fits.waiting == 1 and fits.deferred >= 1 and fits.tokens < 0.0
    assert engine.catch_up(wall=350.0) == [] and fits.waiting == 1  # a second on: in debt
    decided = engine.catch_up(wall=1e6)  # the bucket refilled (and capped)
    assert [u.reason for r in decided for u in r.updates()] == ["model"]
    view = engine.view("L", wall=1e9)
    assert fits.waiting == 0
    assert view.identification.state == "checking" and view.counters.identified == 1
    assert "budget" not in view.identification.why
    assert view.identification.in_force.tau == pytest.approx(40.0, rel=0.3)


def _two_owed(*configs) -> TuningEngine:
    """An engine far below one fit's budget with two loops driven through six moves:
    both owed an assessment."""
    engine = TuningEngine(untrained_agent(0), site=SiteDefaults(fit_share=1e-6))
    for config in configs:
        engine.register(config, wall=0.0)
    for config in configs:
        drive(engine, config.id, moves=6)
    assert engine.table.fits.waiting == 2
    return engine


def test_a_loop_without_a_model_is_assessed_before_a_hint_check(dear_fits):
    """Both owed, one pass's budget (one fit overdraws it): the hint-free loop's
    assessment is made, the hinted loop's waits."""
    engine = _two_owed(hinted("checked"), hint_free("free"))
    fits = engine.table.fits
    engine.catch_up(wall=1e6)  # refilled: a pass's worth, one fit
    assert fits.waiting == 1 and engine.table.slot("checked") in fits.owed
    assert engine.view("free", wall=1e9).counters.identified == 1


def test_segments_that_end_on_a_spent_budget_are_released_unassessed(dear_fits, monkeypatch):
    """A plant trip puts every loop in manual at once: their segments end, and with the
    budget spent they are released without a fit (no stall behind thousands of fits),
    owed nothing, and say why."""
    engine = _two_owed(hint_free("a"), hint_free("b"))
    calls = []
    real = identify.assess
    monkeypatch.setattr(identify, "assess", lambda *a, **k: calls.append(1) or real(*a, **k))
    tb = engine.table
    for loop_id in ("a", "b"):
        s = tb.slot(loop_id)
        sp = float(tb.id_sp[s])
        manual = {"loop_id": loop_id, "t": float(tb.last_t[s]) + H, "sp": sp, "pv": sp,
                  "kp": float(tb.kp[s]), "ki": float(tb.ki[s]), "auto": False}  # fmt: skip
        engine.ingest([manual], wall=3.0)
    assert calls == [] and engine.table.fits.waiting == 0
    for loop_id in ("a", "b"):
        why = engine.view(loop_id, wall=1e9).identification.why
        assert "manual" in why and "identification budget spent" in why, why
        assert tb.rec[tb.slot(loop_id)] == -1  # released


def test_a_removed_or_restarted_loop_is_owed_nothing(dear_fits):
    engine = _two_owed(hint_free("a"), hint_free("b"))
    fits = engine.table.fits
    engine.identify("a", wall=1.0)
    engine.remove("b")
    assert fits.waiting == 0


def test_the_tuner_takes_its_share_from_the_settings_and_reports_the_budget(tmp_path, monkeypatch):
    """PITUNE_IDENTIFY_CPU_SHARE sets the share (0.25 of a core by default; outside (0, 1]
    the tuner does not start); /metrics has the loops waiting, the deferrals and the fits'
    CPU seconds."""
    from fastapi.testclient import TestClient
    from pydantic import ValidationError

    from service.daemon.api import create_app
    from tests.tuner_support import tuner_settings

    assert tuner_settings(tmp_path).identify_cpu_share == 0.25
    monkeypatch.setenv("PITUNE_IDENTIFY_CPU_SHARE", "0")
    with pytest.raises(ValidationError, match="identify_cpu_share"):
        tuner_settings(tmp_path)
    monkeypatch.setenv("PITUNE_IDENTIFY_CPU_SHARE", "0.5")
    kp, ki = gains()
    body = {"id": "TIC-1", "kp": kp, "ki": ki, "sample_period_s": H}
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        assert client.app.state.tuner.engine.table.fits.share == 0.5
        assert client.post("/loops", json=body).status_code == 201
        text = client.get("/metrics").text
    for line in ("pitune_identify_owed_waiting 0.0", "pitune_identify_deferred_total 0.0",
                 "pitune_identify_fit_seconds_total 0.0"):  # fmt: skip
        assert line in text


def test_the_tuner_makes_owed_assessments_between_messages(tmp_path):
    """Eight hint-free loops whose events close in the same batches, through a real bus:
    a pass's budget (10 ms) holds a fit or two, so most assessments are owed; the worker
    makes them when no samples wait, and every loop is identified and tuned."""
    import json

    import numpy as np

    from plant_sim.foptd import FOPTDBatch
    from plant_sim.pi import PIBatch
    from service.daemon.tuner import Tuner
    from service.engine.config import LoopConfig
    from tests.tuner_support import connected_gateway, tuner_settings, wait_until

    n, every = 8, 5.0
    ids = [f"TIC-{i}" for i in range(n)]
    kp, ki = gains()
    tuner = Tuner(tuner_settings(tmp_path, identify_cpu_share=0.05)).start()
    gw = None
    try:
        gw = connected_gateway(tuner.settings)
        for loop_id in ids:
            tuner.register(LoopConfig(id=loop_id, kp=kp, ki=ki, sample_period_s=H))
        plant = FOPTDBatch(np.full(n, K), TAU / H, THETA / H, dt=1.0, noise_std=1.0, seed=3)
        plant.reset(50.0)
        pi = PIBatch(np.full(n, kp), np.full(n, ki * H), dt=1.0)
        pi.initialise(np.full(n, 50.0 / K))
        period = int(round(every * TAU / H))
        sp = 50.0
        for j in range(7 * period):
            if j and j % period == 0:
                sp = 50.0 + (20.0 if (j // period) % 2 else -20.0)
            y = plant.measure()
            batch = {"samples": [{"loop_id": i, "t": j * H, "sp": sp, "pv": float(y[k]),
                                  "kp": kp, "ki": ki} for k, i in enumerate(ids)]}  # fmt: skip
            gw.session.put(gw.keys.batch, json.dumps(batch).encode())
            plant.step(pi.step(sp - y))

        def identified():
            return all(tuner.view(i).counters.identified == 1 for i in ids)

        wait_until(identified, timeout=60.0, what="every loop identified")
        wait_until(lambda: not tuner.table.fits.owed, timeout=60.0, what="nothing owed")
        assert tuner.metrics.value("pitune_identify_deferred_total") > 0
        assert tuner.metrics.value("pitune_identify_owed_waiting") == 0
        assert tuner.metrics.value("pitune_identify_fit_seconds_total") > 0
        for loop_id in ids:
            assert tuner.view(loop_id).identification.in_force.tau == pytest.approx(TAU, rel=0.3)
    finally:
        if gw is not None:
            gw.close()
        tuner.stop()


def test_a_loop_assessed_when_due_is_owed_nothing_and_one_no_longer_identified_is_skipped(
    dear_fits, monkeypatch
):
    """Budget back: a's next move closes its event and assesses it there, so it leaves
    the queue (no second fit of the same data); b's identification turned off while
    owed: the catch-up passes it by."""
    engine = _two_owed(hint_free("a"), hint_free("b"))
    tb, fits = engine.table, engine.table.fits
    calls = []
    real = identify.assess
    monkeypatch.setattr(identify, "assess", lambda *a, **k: calls.append(1) or real(*a, **k))
    fits.tokens = 1.0  # (capped at the next refill, still > 0)
    a = tb.slot("a")
    sp = float(tb.id_sp[a]) + 20.0  # a setpoint move: a's event closes
    move = {"loop_id": "a", "t": float(tb.last_t[a]) + H, "sp": sp, "pv": sp - 20.0,
            "kp": float(tb.kp[a]), "ki": float(tb.ki[a])}  # fmt: skip
    engine.ingest([move], wall=400.0)
    assert len(calls) == 1 and a not in fits.owed and fits.waiting == 1
    tb.watch[tb.slot("b")] = False  # (a patch of guard.identify does this)
    fits.tokens = 1.0
    engine.catch_up(wall=401.0)
    assert len(calls) == 1 and fits.waiting == 0
    assert engine.view("b", wall=1e9).counters.identified == 0
