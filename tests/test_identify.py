"""Closed-loop identification (issue 13): the fit, hint-free registration through the
engine, bad data that must not identify, hints checked, snapshots and the envelope guard
(integrating loops: tests/test_integrating.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch
from plant_sim.tunings import simc_paper, to_parallel
from service.agent import untrained_agent
from service.engine import LoopConfig, SiteDefaults, TuningEngine
from service.engine.identify import assess, reconstruct_op
from service.wire.protocol import LoopStatus

pytestmark = pytest.mark.timeout(120)

K, TAU, THETA, H = 2.0, 40.0, 10.0, 4.0
"""The loop of most tests: 10 samples per time constant."""


def gains(k=K, tau=TAU, theta=THETA, share=0.5):
    kp, ki = to_parallel(*simc_paper(k, tau, theta))
    return float(share * kp), float(share * ki)


def drive(
    engine: TuningEngine,
    loop_id: str = "L",
    *,
    k=K,
    tau=TAU,
    theta=THETA,
    h=H,
    moves=6,
    every=5.0,
    size=20.0,
    noise=1.0,
    seed=0,
    auto=True,
    saturated=False,
    frozen_pv=False,
    send_op=False,
    tau_end=None,
    integrating=False,
    t0=0.0,
    ramp=0.0,
    u_max=np.inf,
    u_min=-np.inf,
    quantum=0.0,
    advisory_applied=True,
) -> list:
    """Run one simulated loop through the engine: ``moves`` setpoint moves of +-``size``
    every ``every`` time constants (each a ramp over ``ramp`` time constants, 0: a step;
    a list: the i-th move's, the last for the moves beyond it; ``u_min``, ``u_max``: the
    DCS's output limits, which the samples do not show; ``quantum``: the PV's resolution;
    ``advisory_applied`` False: the simulated DCS ignores advisory messages, as a gateway
    does); returns the gain updates published."""  # fmt: skip
    kp, ki = engine.view(loop_id, wall=0.0).kp, engine.view(loop_id, wall=0.0).ki
    if integrating:
        plant = FOPTDBatch(1.0, 1e9, theta / h, dt=1.0, noise_std=noise, seed=seed)
    else:
        plant = FOPTDBatch(k, tau / h, theta / h, dt=1.0, noise_std=noise, seed=seed,
                           max_theta=theta / h)  # fmt: skip
    plant.reset(50.0)
    pi = PIBatch(kp, ki * h, dt=1.0, u_min=u_min, u_max=u_max)
    pi.initialise(0.0 if integrating else 50.0 / k)
    n = int(round((moves + 1) * every * tau / h))
    target, updates = 50.0, []
    sp, rate = target, 0.0
    for j in range(n):
        t = t0 + j * h
        if j and j % int(round(every * tau / h)) == 0:
            move = j // int(round(every * tau / h))
            target = 50.0 + size * (1 if move % 2 else -1)
            over = ramp[min(move, len(ramp)) - 1] if isinstance(ramp, list) else ramp
            rate = abs(target - sp) / max(over * tau / h, 1.0)
        sp = min(max(target, sp - rate), sp + rate)
        if tau_end is not None:
            plant.set_params(tau=(tau + (tau_end - tau) * j / n) / h)
        y = float(plant.measure()[0])
        if frozen_pv:
            y = 50.0
        elif quantum:  # the PV in coarse steps (an integer register, an ADC's)
            y = quantum * round(y / quantum)
        sample = {"loop_id": loop_id, "t": t, "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0] / h), "auto": auto, "saturated": saturated}  # fmt: skip
        # the controller acts with the gains the sample reports (a DCS's cycle); an
        # update reaches it for the next sample
        u = pi.step(sp - y) if auto else np.array([50.0 / k])
        if send_op:
            sample["op"] = float(u[0])
        new = engine.ingest([sample], wall=float(j))
        for up in new:
            if advisory_applied or up.mode != "advisory":
                pi.set_gains(up.kp, up.ki * h)
        updates += new
        if integrating:
            plant.step(u * (k * h) * 1e9)  # a lag of tau 1e9 samples integrates k u dt
        else:
            plant.step(u)
    return updates


def hint_free(loop_id="L", **guard) -> LoopConfig:
    kp, ki = gains()
    return LoopConfig(id=loop_id, kp=kp, ki=ki, sample_period_s=H, guard=guard)


def hinted(loop_id="L", k_hat=K, tau_hat=TAU, **guard) -> LoopConfig:
    """A hinted loop whose hint is checked (identification is opt-in with a hint)."""
    kp, ki = gains()
    scaling = {"k_hat": k_hat, "tau_hat": tau_hat, "pv_scale": 20.0}
    guard = {"identify": True, **guard}
    return LoopConfig(id=loop_id, kp=kp, ki=ki, sample_period_s=H, scaling=scaling, guard=guard)


# -- the numerics --------------------------------------------------------------------
def test_fit_recovers_an_foptd_plant_from_closed_loop_data_with_a_reconstructed_output():
    kp, ki = gains()
    plant = FOPTDBatch(K, TAU, THETA, dt=H, noise_std=1.0, seed=3)
    plant.reset(50.0)
    pi = PIBatch(kp, ki, dt=H)
    pi.initialise(50.0 / K)
    n, every = 300, 50
    sp = 50.0 + 20.0 * np.where((np.arange(n) // every) % 2 == 1, 1.0, -1.0)
    sp[:every] = 50.0
    pv = np.empty(n)
    for j in range(n):
        pv[j] = plant.measure()[0]
        plant.step(pi.step(sp[j] - pv[j]))
    t = np.arange(n) * H
    op = reconstruct_op(t, sp - pv, np.full(n, kp), np.full(n, ki))
    starts = list(range(every, n, every))
    result = assess(t[every - 1 :], sp[every - 1 :], pv[every - 1 :], op[every - 1 :],
                    [s - every + 1 for s in starts])  # fmt: skip
    m = result.model
    assert result.why == "" and m.confident and m.confidence > 0.5
    assert m.k == pytest.approx(K, rel=0.1) and m.tau == pytest.approx(TAU, rel=0.2)
    assert m.noise == pytest.approx(1.0, rel=0.2) and not m.integrating
    assert all(ev.excited for ev in result.events)


# -- hint-free registration -----------------------------------------------------------
def test_a_hint_free_loop_is_identified_then_tuned_and_survives_a_restart():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    assert engine.view("L", wall=0.0).scaling is None
    updates = drive(engine, moves=3)
    view = engine.view("L", wall=0.0)
    if view.counters.identified:  # gains only once identified
        assert all(u.t >= view.identification.in_force_t for u in updates)
    else:
        assert updates == []
    later = drive(engine, moves=3, seed=1)  # a new plant clock: t from 0 again
    if not view.counters.identified:
        assert all(u.t >= engine.view("L", wall=0.0).identification.in_force_t for u in later)
    updates += later
    view = engine.view("L", wall=1e9)
    ident = view.identification
    assert view.counters.identified == 1, ident.why
    assert ident.in_force.k == pytest.approx(K, rel=0.3)
    assert ident.in_force.tau == pytest.approx(TAU, rel=0.3)
    assert view.scaling.time_unit_s == pytest.approx(ident.in_force.tau / 0.5)
    # the model's first tuning (first_tuning.py), then the agent's steps
    assert updates and all(u.reason == "agent" for u in updates if u.reason != "model")
    _, audit = engine.drain_changes()
    assert [r[5] for r in audit].count("identified") == 1
    # the runtime snapshot carries it over a restart
    ((loop_id, hidden, runtime),) = engine.snapshot()
    again = TuningEngine(untrained_agent(0))
    again.restore(hint_free(), kp=view.kp, ki=view.ki, seq=view.seq, hidden=hidden,
                  runtime=runtime, wall=0.0)  # fmt: skip
    restored = again.view("L", wall=0.0)
    assert restored.scaling == view.scaling
    assert restored.identification.in_force == ident.in_force
    assert restored.counters.identified == 1
    # and identification starts over on request
    again.identify("L", wall=0.0)
    assert again.view("L", wall=0.0).scaling is None
    assert again.view("L", wall=0.0).status in (LoopStatus.identifying, LoopStatus.stale)


def test_a_loop_that_never_sent_a_sample_waits_for_samples():
    """Status ``waiting``, and identification says so (it said "waiting for a setpoint
    move"); its first sample, without a move, leaves it waiting for one."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    view = engine.view("L", wall=0.0)
    assert view.status == LoopStatus.waiting
    assert view.identification.why.startswith("waiting for samples: none received")
    engine.ingest([{"loop_id": "L", "t": 0.0, "sp": 50.0, "pv": 50.0}], wall=0.0)
    assert engine.view("L", wall=0.0).identification.why.startswith("waiting for a setpoint move")


def test_hint_free_loop_takes_no_step_and_publishes_nothing_while_identifying():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    assert drive(engine, moves=1) == []
    view = engine.view("L", wall=float(10**6))
    assert view.counters.steps == 0
    engine.ingest([{"loop_id": "L", "t": 1e6, "sp": 50.0, "pv": 50.0}], wall=1e6)
    assert engine.view("L", wall=1e6).status == LoopStatus.identifying


# -- bad data ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("case", "why"),
    [
        ({"auto": False}, "manual"),
        ({"saturated": True}, "saturated"),
        ({"frozen_pv": True}, "frozen"),
        # every other move asks the output for 35, the valve stops at 28 (no op, no flag)
        ({"u_max": 28.0}, "an output at a limit the samples do not show"),
        ({"size": 0.3}, "too small for the noise"),
    ],
)
def test_bad_data_yields_no_identification_and_says_why(case, why):
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    updates = drive(engine, moves=6, **case)
    view = engine.view("L", wall=float(10**4))
    assert updates == [] and view.counters.identified == 0 and view.scaling is None
    assert view.status in (LoopStatus.identifying, LoopStatus.stale)
    assert why in view.identification.why, view.identification.why
    if "size" in case:  # the loop's own moves will not do: what will
        assert "output step in manual" in view.identification.why
    model = view.identification.model
    assert model is None or not model.confident


@pytest.mark.parametrize("ramp", [0.3, 1.0])
def test_a_ramp_faster_than_the_loop_identifies_as_a_step_does(ramp):
    """A setpoint ramping one change a sample over ``ramp`` time constants (a DCS's
    setpoint rate limit) is one event from its first change, its move the whole ramp;
    faster than tau + theta it tells tau from the dead time (over 3 tau it does not: the
    lumped model below)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=6, ramp=ramp)
    view = engine.view("L", wall=float(10**4))
    ident = view.identification
    assert view.counters.identified == 1 and ident.model.confident
    assert ident.model.k == pytest.approx(K, rel=0.05)
    assert ident.model.tau == pytest.approx(TAU, rel=0.1)
    assert ident.model.theta == pytest.approx(THETA, abs=0.3 * THETA)
    ramped = [ev for ev in ident.events if ev.move]
    # the first move from the start's 50 to 70, each later one between 30 and 70
    assert ramped and all(abs(ev.move) == pytest.approx(40.0) for ev in ramped[1:])
    assert all(0.5 * ramp * TAU <= ev.ramp_s <= ramp * TAU + H for ev in ramped)


# -- hints checked -----------------------------------------------------------------------
@pytest.mark.parametrize("factor", [("k_hat", 3.0), ("tau_hat", 1 / 3)])
def test_a_wrong_hint_is_flagged_and_rescaled_on_request(factor):
    name, f = factor
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted("A", **{name: {"k_hat": K, "tau_hat": TAU}[name] * f}), wall=0.0)
    engine.register(
        hinted("B", auto_rescale=True, **{name: {"k_hat": K, "tau_hat": TAU}[name] * f}),
        wall=0.0,
    )
    drive(engine, "A", moves=6)
    drive(engine, "B", moves=6)
    a, b = engine.view("A", wall=1e9), engine.view("B", wall=1e9)
    assert a.counters.mismatches == 1 and a.identification.mismatch
    assert a.status in (LoopStatus.hint_mismatch, LoopStatus.out_of_envelope, LoopStatus.stale)
    assert b.counters.identified >= 1 and not b.identification.mismatch
    assert b.counters.mismatches == 1  # flagged, then rescaled
    assert b.scaling.apparent_gain(K) == pytest.approx(0.5, rel=0.3)
    assert b.scaling.apparent_tau(TAU) == pytest.approx(0.5, rel=0.3)
    _, audit = engine.drain_changes()
    reasons = [(r[0], r[5]) for r in audit]
    assert ("A", "mismatch") in reasons and ("B", "rescaled") in reasons


def test_the_sites_defaults_check_and_rescale_hinted_loops_that_left_it_unset():
    """SiteDefaults (the tuner's identify_hinted_loops and auto_rescale): a hinted loop
    whose registration leaves guard.identify and guard.auto_rescale unset is identified
    and, its hint 3x off, rescaled; a loop's own setting wins either way."""
    engine = TuningEngine(untrained_agent(0), site=SiteDefaults(True, True))
    kp, ki = gains()

    def wrong(loop_id, **guard):
        scaling = {"k_hat": K, "tau_hat": 3.0 * TAU, "pv_scale": 20.0}
        return LoopConfig(id=loop_id, kp=kp, ki=ki, sample_period_s=H, scaling=scaling,
                          guard=guard)  # fmt: skip

    engine.register(wrong("site"), wall=0.0)
    engine.register(wrong("flag_only", auto_rescale=False), wall=0.0)
    engine.register(wrong("own_off", identify=False), wall=0.0)
    for loop_id in ("site", "flag_only", "own_off"):
        drive(engine, loop_id, moves=6)
    site, flag_only, off = (engine.view(i, wall=1e9) for i in ("site", "flag_only", "own_off"))
    assert site.counters.mismatches == 1 and not site.identification.mismatch
    assert site.scaling.apparent_tau(TAU) == pytest.approx(0.5, rel=0.3)  # rescaled
    assert flag_only.counters.mismatches == 1 and flag_only.identification.mismatch
    assert flag_only.scaling.apparent_tau(TAU) == pytest.approx(0.5 / 3, rel=0.3)  # kept
    assert off.identification.state == "off" and off.counters.mismatches == 0
    # the default engine checks hinted loops and flags them, rescaling none
    plain = TuningEngine(untrained_agent(0))
    plain.register(wrong("site"), wall=0.0)
    drive(plain, "site", moves=6)
    view = plain.view("site", wall=1e9)
    assert view.identification.mismatch and view.counters.mismatches == 1
    assert view.scaling.apparent_tau(TAU) == pytest.approx(0.5 / 3, rel=0.3)  # kept


def test_a_right_hint_is_confirmed_not_flagged():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(k_hat=K * 1.3, tau_hat=TAU / 1.3), wall=0.0)
    drive(engine, moves=6)
    view = engine.view("L", wall=1e9)
    assert view.identification.model is not None and view.identification.model.confident
    assert view.counters.mismatches == 0 and not view.identification.out_of_envelope


def test_a_hint_is_checked_at_event_closes_only_and_from_its_last_confident_model(
    monkeypatch,
):
    """The cost rule (service.engine.watch.closely): a loop on its registered hint is
    assessed once per setpoint move (at the close of the event), not during events as a
    hint-free loop is, and once a model was confident its fits start from that model
    instead of the grid search."""
    from service.engine import identify

    calls: dict[str, list] = {"hinted": [], "free": []}
    real = identify.assess

    def counted(t, sp, pv, op, starts, start=None, *rest):
        calls[loop[0]].append(start)
        return real(t, sp, pv, op, starts, start, *rest)

    monkeypatch.setattr(identify, "assess", counted)
    for loop in (("hinted", hinted()), ("free", hint_free())):
        config = loop[1]
        engine = TuningEngine(untrained_agent(0))
        engine.register(config, wall=0.0)
        drive(engine, moves=6)
    # moves 3-6 close an event with one before it (two are needed): one assessment each;
    # the hint-free loop is also assessed during its events until identified
    assert len(calls["hinted"]) == 4
    assert len(calls["free"]) > 4
    first = next(i for i, start in enumerate(calls["hinted"]) if start is not None)
    assert all(start is not None for start in calls["hinted"][first:])
    assert calls["hinted"][0] is None  # no model yet: the grid search


# -- the envelope (integrating loops: tests/test_integrating.py) ---------------------------
@pytest.mark.parametrize(
    ("tau_rse", "prediction", "paused"),
    [(0.05, 2.0, True), (0.3, 1.0, True), (0.3, 11.0, False)],
    ids=["precise-but-inconsistent", "consistent-but-imprecise", "neither"],
)
def test_an_unconfident_model_pauses_only_when_it_fails_one_check_of_two(
    tau_rse, prediction, paused
):
    """A model of a plant 10x the hint's gain that passes every check but precision, or
    but consistency, pauses the loop (a drifting plant); one that fails both (the earlier
    events' model missed the next by 11x the noise: load steps at the plant input) is
    not used (service.engine.model_use.envelope)."""
    from service.engine import model_use
    from service.engine.identify import Model

    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(), wall=0.0)
    tb, s = engine.table, engine.table.slot("L")
    m = Model(k=10 * K, tau=TAU, theta=THETA, noise=1.0, move=20.0, r2=0.95, k_rse=0.05,
              tau_rse=tau_rse, events=3, prediction=prediction)  # fmt: skip
    model_use.envelope(tb, s, m, 100.0, 1.0, sure=False)
    assert bool(tb.out_env[s]) is paused
    assert engine.view("L", wall=1.0).counters.envelope_pauses == int(paused)


def test_a_plant_gone_out_of_the_agents_envelope_is_paused():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=4)
    assert engine.view("L", wall=1e9).counters.identified == 1
    # the plant slows down 5x (a fouled exchanger, a valve change): out of the box
    drive(engine, tau=5 * TAU, moves=5, seed=2, t0=1e5)
    view = engine.view("L", wall=1e9)

    assert view.counters.envelope_pauses >= 1 and view.identification.out_of_envelope
    assert math.isfinite(view.identification.model.tau)


# -- through the daemon's API (unchanged daemon: the engine's view and statuses) -------------
def test_the_daemon_registers_a_hint_free_loop_and_shows_its_identification(tmp_path):
    from fastapi.testclient import TestClient

    from service.daemon.api import create_app
    from tests.tuner_support import tuner_settings

    kp, ki = gains()
    body = {"id": "TIC-7", "kp": kp, "ki": ki, "sample_period_s": H}
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        r = client.post("/loops", json=body)
        assert r.status_code == 201, r.text
        view = r.json()
        assert view["scaling"] is None and view["rl_period_s"] is None
        assert view["identification"]["state"] == "identifying"
        assert view["config"]["scaling"] is None and view["config"]["guard"]["kp_min"] is None
        assert 'pitune_loops_by_status{status="identifying"}' in client.get("/metrics").text
    with TestClient(create_app(tuner_settings(tmp_path))) as client:  # restored from the store
        view = client.get("/loops/TIC-7").json()
        assert view["identification"]["state"] == "identifying"


def test_the_tuners_settings_turn_hint_checks_on_for_loops_that_leave_them_unset(
    tmp_path, monkeypatch
):
    """PITUNE_IDENTIFY_HINTED_LOOPS / PITUNE_AUTO_RESCALE: a hinted loop registered
    without guard.identify is checked, and says so; the stored config keeps the loop's
    own choice (null), so a restart without the settings turns the check off again."""
    from fastapi.testclient import TestClient

    from service.daemon.api import create_app
    from tests.tuner_support import tuner_settings

    kp, ki = gains()
    scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
    body = {"id": "FIC-1", "kp": kp, "ki": ki, "sample_period_s": H, "scaling": scaling}
    own = {**body, "id": "FIC-2", "guard": {"identify": False}}
    monkeypatch.setenv("PITUNE_IDENTIFY_HINTED_LOOPS", "true")
    monkeypatch.setenv("PITUNE_AUTO_RESCALE", "true")
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        for registration in (body, own):
            assert client.post("/loops", json=registration).status_code == 201
        site, mine = (client.get(f"/loops/{i}").json() for i in ("FIC-1", "FIC-2"))
        assert site["identification"]["state"] == "checking"
        assert site["config"]["guard"]["identify"] is None
        assert site["config"]["guard"]["auto_rescale"] is None
        assert mine["identification"]["state"] == "off"
        tuner = client.app.state.tuner
        assert tuner.engine.table.site.identify_hinted and tuner.engine.table.site.auto_rescale
    monkeypatch.setenv("PITUNE_IDENTIFY_HINTED_LOOPS", "false")
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        assert client.get("/loops/FIC-1").json()["identification"]["state"] == "off"


def test_samples_out_of_order_or_on_a_new_clock_never_break_identification():
    """Fuzzed samples (times going back, new plant clocks, resets, error-only samples in
    between) reach a segment's assessment without an exception, and are accepted and
    rejected exactly as by a loop that does not identify."""
    import random

    engines = [TuningEngine(untrained_agent()) for _ in range(2)]
    for eng in engines:
        eng.register(hint_free(), wall=0.0)
    engines[1].table.watch[engines[1].table.slot("L")] = False  # the twin: no identification
    r = random.Random(2)
    t, sp = 0.0, 50.0
    for j in range(600):
        t += r.choice([4.0] * 20 + [-30.0, -400.0, 0.0, 1e-9])
        if r.random() < 0.05:
            sp = 50.0 + r.choice([-20.0, 20.0])
        reset = r.random() < 0.01
        if r.random() < 0.7:
            smp = {"loop_id": "L", "t": t, "sp": sp, "pv": sp + r.gauss(0, 3), "kp": 1.0,
                   "ki": 0.05}  # fmt: skip
        else:
            smp = {"loop_id": "L", "t": t, "e": r.gauss(0, 3)}
        for eng in engines:
            if reset:
                eng.reset("L", wall=float(j))
            eng.ingest([smp], wall=float(j))
    counts = [eng.view("L", wall=600.0).counters for eng in engines]
    assert (counts[0].samples, counts[0].rejected) == (counts[1].samples, counts[1].rejected)
    assert counts[0].rejected > 0 and counts[0].samples > 100


def test_a_window_whose_times_do_not_increase_is_not_fitted():
    t = np.arange(40.0)
    t[25:] -= 100.0  # a new plant clock inside the segment
    pv = np.sin(t / 5.0)
    op = np.cos(t / 7.0)
    out = assess(t, 50.0 + 0 * t, pv, op, [0, 10, 20, 30])
    assert out.model is None and "not increasing" in out.why


def test_identification_is_on_by_default_for_every_loop_off_where_a_loop_or_site_says():
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    kp, ki = gains()
    plain = LoopConfig(
        id="H", kp=kp, ki=ki, sample_period_s=H,
        scaling={"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0},
    )  # fmt: skip
    engine.register(plain, wall=0.0)
    own = plain.model_copy(
        update={"id": "OWN", "guard": plain.guard.model_copy(update={"identify": False})}
    )
    engine.register(own, wall=0.0)
    quiet = TuningEngine(untrained_agent(0), site=SiteDefaults(identify_hinted=False))
    quiet.register(plain, wall=0.0)
    watch, slot = engine.table.watch, engine.table.slot_of
    assert watch[slot[hint_free().id]] and watch[slot["H"]] and not watch[slot["OWN"]]
    assert not quiet.table.watch[quiet.table.slot_of["H"]]
