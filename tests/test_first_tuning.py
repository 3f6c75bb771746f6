"""The first tuning from an identified model (service/engine/first_tuning.py): when a
hint-free loop's model comes into force, gains well below the model's SIMC tuning are
raised to it in one published, audited change that verify-or-rollback judges; gains
already near or above it are left to the agent; the guard's switch turns it off."""

from __future__ import annotations

import json

import pytest

from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine
from service.engine.first_tuning import model_gains
from tests.test_identify import TAU, H, K, drive, gains

pytestmark = pytest.mark.timeout(120)


def engine_with(share: float, mode: str = "auto", **guard) -> TuningEngine:
    """A hint-free loop whose registered gains are ``share`` of the true SIMC tuning."""
    engine = TuningEngine(untrained_agent(0))
    kp, ki = gains(share=share)
    engine.register(
        LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H, mode=mode, guard=guard), wall=0.0
    )
    return engine


def test_a_sluggish_loop_gets_the_models_tuning_in_one_verified_change():
    engine = engine_with(0.25)
    updates = drive(engine, moves=6, every=12.0)  # responses complete: 2 RL periods, 11 tau
    view = engine.view("L", wall=1e9)
    assert view.counters.identified == 1
    _, audit = engine.drain_changes()
    rows = [r for r in audit if r[5] == "model"]
    detail = json.loads(rows[0][10])
    assert detail["after"] == "identified" and detail["rule"].startswith("simc")
    assert "pred_iae" in detail["predicted"]
    first = updates[0]
    assert first.reason == "model" and first.mode == "auto" and first.t == rows[0][2]
    model = (detail["k"], detail["tau"], detail["theta"])
    assert (first.kp, first.ki) == pytest.approx(model_gains(*model))
    kp0, ki0 = gains(share=0.25)
    assert first.kp > 3 * kp0 and first.ki > 3 * ki0  # a jump, not a guard step of 1.5x
    assert "reason=model" in first.why and "rule=simc" in first.why
    # the first model came from 3 moves (tau 29 s for 40, standard error 13 %: provisional);
    # a later one, 6x as precise, refines it (model_check.refined) and its tuning follows
    later = [json.loads(r[10]) for r in rows[1:]]
    assert [d["after"] for d in later] == ["followed"]
    assert later[0]["tau"] == pytest.approx(TAU, rel=0.05) and detail["tau"] < 0.8 * TAU
    assert view.identification.in_force.tau == later[0]["tau"]
    # judged like any change: a verdict row covers its seq
    judged = [json.loads(r[10]) for r in audit if r[5] in ("verified", "rollback")]
    assert any(d["seqs"][0] <= first.seq <= d["seqs"][1] for d in judged), judged
    # and the agent waits for that verdict (one change judged at a time)
    verdict_t = min(r[2] for r in audit if r[5] in ("verified", "rollback") and r[2] > first.t)
    agent = [u for u in updates if u.reason == "agent"]
    assert agent and min(u.t for u in agent) >= verdict_t


def test_gains_near_or_above_the_models_tuning_are_left_to_the_agent():
    engine = engine_with(0.8)  # within one guard step (1.5x) of the model's tuning
    updates = drive(engine, moves=4)
    view = engine.view("L", wall=1e9)
    assert view.counters.identified == 1 and view.counters.steps > 0
    # the agent's steps (published, or held by the model check), no model tuning
    assert all(u.reason == "agent" for u in updates)


def test_the_guard_switch_turns_it_off_and_advisory_loops_get_a_proposal():
    off = engine_with(0.25, model_tuning=False)
    assert all(u.reason == "agent" for u in drive(off, moves=4))
    assert off.view("L", wall=1e9).counters.identified == 1
    advisory = engine_with(0.25, mode="advisory")
    updates = drive(advisory, moves=4)
    first = updates[0]
    assert first.reason == "model" and first.mode == "advisory"
    # a proposal: the tuner kept the registered gains until the gateway reported them
    assert (first.kp - first.dkp) == pytest.approx(gains(share=0.25)[0])


def test_a_rescale_sets_the_models_tuning_even_below_the_gains_in_force():
    """A tau hint 3x too fast: the agent's gains (here 3x the textbook's) were tuned for
    a faster plant; the rescale replaces them by the model's tuning, lowering both."""
    engine = TuningEngine(untrained_agent(0))
    kp, ki = gains(share=3.0)
    scaling = {"k_hat": K, "tau_hat": TAU / 3, "pv_scale": 20.0}
    guard = {"identify": True, "auto_rescale": True}
    engine.register(
        LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H, scaling=scaling, guard=guard),
        wall=0.0,
    )
    updates = drive(engine, moves=6, every=12.0)
    view = engine.view("L", wall=1e9)
    assert view.counters.mismatches == 1 and view.counters.identified >= 1
    model = [u for u in updates if u.reason == "model"]
    assert model, [u.reason for u in updates]
    m = view.identification.in_force
    kp_m, ki_m = model_gains(m.k, m.tau, m.theta)
    assert (model[0].kp, model[0].ki) == pytest.approx((kp_m, ki_m))
    assert model[0].dkp < 0 and model[0].dki < 0
    # the guard's bounds are now the model band (guard.model_band, 1.5x either way)
    tb, s = engine.table, engine.table.slot("L")
    bounds = (tb.kp_min[s], tb.kp_max[s], tb.ki_min[s], tb.ki_max[s])
    assert bounds == pytest.approx((kp_m / 1.5, kp_m * 1.5, ki_m / 1.5, ki_m * 1.5))
    _, audit = engine.drain_changes()
    row = next(r for r in audit if r[5] == "model")
    assert json.loads(row[10])["after"] == "rescaled"


def test_the_model_band_can_be_turned_off_and_never_widens_the_users_bounds():
    kp, ki = gains(share=0.25)
    off = engine_with(0.25, model_band=None)
    narrow = engine_with(0.25, kp_max=kp * 4.5)  # below the band's top (~6x kp here)
    for engine in (off, narrow):
        drive(engine, moves=4)
        assert engine.view("L", wall=1e9).counters.identified == 1
    tb, s = off.table, off.table.slot("L")
    assert tb.kp_max[s] > 10 * kp and tb.ki_max[s] > 10 * ki  # the agent's range: no band
    tb, s = narrow.table, narrow.table.slot("L")
    m = narrow.view("L", wall=1e9).identification.in_force
    kp_m, ki_m = model_gains(m.k, m.tau, m.theta)
    assert tb.kp_max[s] == pytest.approx(kp * 4.5) and tb.kp_min[s] == pytest.approx(kp_m / 1.5)
    assert tb.ki_max[s] == pytest.approx(ki_m * 1.5)


def test_a_loop_paused_out_of_the_envelope_is_paused_on_the_models_tuning():
    """Right K and tau, but dead time 3 tau (beyond the box's 1.5): paused, and its gains
    set to the model's tuning rather than left where they were (here a quarter of it)."""
    engine = TuningEngine(untrained_agent(0))
    kp, ki = gains(theta=3 * TAU, share=0.25)
    scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
    engine.register(
        LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H, scaling=scaling,
                   guard={"identify": True}),
        wall=0.0,
    )  # fmt: skip
    updates = drive(engine, theta=3 * TAU, moves=6, every=12.0)
    view = engine.view("L", wall=1e9)
    assert view.identification.out_of_envelope and view.counters.envelope_pauses == 1
    model = [u for u in updates if u.reason == "model"]
    assert len(model) == 1, [u.reason for u in updates]
    m = view.identification.model
    assert (view.kp, view.ki) == pytest.approx(model_gains(m.k, m.tau, m.theta), rel=0.3)
    _, audit = engine.drain_changes()
    row = next(r for r in audit if r[5] == "model")
    assert json.loads(row[10])["after"] == "out_of_envelope"


def test_an_advisory_models_tuning_is_judged_only_once_accepted():
    """A model's tuning proposed in advisory is no change the loop runs with: a verdict
    (an oscillation of the gains in force) until it is accepted must not refute the model
    behind it (the review R1's S01: the cure refuted, a near-exact later model refused as
    like it). Accepted, its seq is the model's tuning's, as in auto."""
    engine = engine_with(0.25, mode="advisory")
    first = drive(engine, moves=4, advisory_applied=False)[0]
    assert first.reason == "model"
    ident = engine.table.ident[engine.table.slot_of["L"]]
    assert ident.tuned is not None and ident.tuned_seq == -1
    proposal = engine.view("L", wall=1e9).proposal
    assert proposal is not None and proposal.reason == "model"
    accepted = engine.accept("L", proposal.seq, wall=1e9)
    assert ident.tuned_seq == int(accepted.seq[0]) > proposal.seq
