"""The tuner in-process on a real Zenoh bus (loopback, own port per test)."""

import contextlib
import json
import logging
import math
import queue
from collections import Counter

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plant_sim import FOPTDBatch, PIBatch
from service.daemon.bus import Kind
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.engine.patch import LoopPatch
from service.wire.decode import Rejection
from service.wire.protocol import GainsBatch, GainsMessage, Mode, RejectReason, UpdateReason
from tests.tuner_support import connected_gateway, loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def bus(tmp_path):
    """A started tuner and a gateway peer connected to it."""
    tuner = Tuner(tuner_settings(tmp_path)).start()
    gateway = None
    try:
        gateway = connected_gateway(tuner.settings)
        yield tuner, gateway
    finally:
        if gateway is not None:
            gateway.close()
        tuner.stop()


def received(tuner, n):
    """Wait until the tuner has handled ``n`` sample messages (accepted or not)."""
    wait_until(
        lambda: tuner.metrics.value("pitune_samples_received_total") >= n, what=f"{n} samples"
    )
    assert tuner.metrics.value("pitune_samples_received_total") == n


def test_one_rl_step_per_period_published_as_gains(bus):
    tuner, gw = bus
    tuner.register(LoopConfig(**loop_body("LIC-101")))
    for i in range(400):
        gw.send("LIC-101", {"t": 1000.0 + i, "sp": 55.0, "pv": 54.0})
    first, second = gw.next_gains(), gw.next_gains()
    assert (first.seq, first.t, second.seq, second.t) == (1, 1165.0, 2, 1330.0)
    assert first.mode is Mode.auto and first.reason is UpdateReason.agent
    assert first.kp == pytest.approx(0.5 + first.dkp) and first.ki == pytest.approx(
        0.01 + first.dki
    )
    assert second.kp == pytest.approx(first.kp + second.dkp)
    ok, state = gw.state("LIC-101")
    assert ok and state["seq"] == 2 and state["last_t"] == 1399.0 and state["status"] == "tuning"
    assert (state["kp"], state["ki"]) == (second.kp, second.ki)
    view = tuner.view("LIC-101")
    assert view.counters.samples == 400 and view.counters.steps == 2
    history = tuner.history("LIC-101", 0, 10).items
    assert [(e.reason, e.seq) for e in history] == [("agent", 2), ("agent", 1), ("registered", 0)]
    assert (history[0].kp_old, history[0].kp_new) == (first.kp, second.kp)
    assert tuner.metrics.value("pitune_updates_published_total", mode="auto") == 2


def test_loops_due_together_share_one_agent_call(bus):
    tuner, gw = bus
    ids = [f"L{i}" for i in range(5)]
    for loop_id in ids:
        tuner.register(LoopConfig(**loop_body(loop_id, sample_period_s=165.0)))
    for t in (0.0, 165.0):
        batch = {"samples": [{"loop_id": i, "t": t, "e": 0.5} for i in ids]}
        gw.session.put(gw.keys.batch, json.dumps(batch).encode())
    got = sorted(gw.next_gains().loop_id for _ in ids)
    assert got == ids
    assert tuner.metrics.value("pitune_inference_batch_loops_count") == 1
    assert tuner.metrics.value("pitune_inference_batch_loops_sum") == 5
    assert tuner.metrics.value("pitune_inference_batch_seconds_count") == 1


def test_advisory_is_marked_and_frozen_is_silent(bus):
    tuner, gw = bus
    tuner.register(LoopConfig(**loop_body("ADV", mode="advisory")))
    tuner.register(LoopConfig(**loop_body("FRZ", mode="frozen")))
    for i in range(200):
        for loop_id in ("ADV", "FRZ"):
            gw.send(loop_id, {"t": float(i), "e": 1.0})
    msg = gw.next_gains()
    assert (msg.loop_id, msg.mode) == ("ADV", Mode.advisory)
    received(tuner, 400)
    assert tuner.view("ADV").kp == 0.5  # advisory updates are never assumed applied
    assert tuner.view("FRZ").status.value == "frozen"
    assert tuner.view("FRZ").counters.steps == 0
    tuner.reset("ADV")  # the control: on the same path, after anything of FRZ's
    control = gw.next_gains()
    assert (control.loop_id, control.reason) == ("ADV", UpdateReason.reset), "FRZ is silent"


def test_reset_publishes_the_registered_gains(bus):
    tuner, gw = bus
    tuner.register(LoopConfig(**loop_body("LIC-101")))
    for i in range(170):
        gw.send("LIC-101", {"t": float(i), "e": 2.0})
    step = gw.next_gains()
    view = tuner.reset("LIC-101")
    msg = gw.next_gains()
    assert (msg.reason, msg.seq, msg.kp, msg.ki) == (UpdateReason.reset, 2, 0.5, 0.01)
    assert (msg.dkp, msg.dki) == pytest.approx((0.5 - step.kp, 0.01 - step.ki))
    assert view.hidden_norm == 0.0 and view.int_e == 0.0 and view.status.value == "waiting"


def test_a_reset_is_not_undone_by_the_gains_the_gateway_still_reports(bus):
    tuner, gw = bus
    tuner.register(LoopConfig(**loop_body("AUTO")))
    tuner.register(LoopConfig(**loop_body("FRZ", mode="frozen")))
    for i in range(170):
        gw.send("AUTO", {"t": float(i), "e": 2.0})
    step = gw.next_gains()
    gw.send("AUTO", {"t": 170.0, "e": 2.0, "kp": step.kp, "ki": step.ki})  # applied
    tuner.reset("AUTO")
    assert gw.next_gains().reason is UpdateReason.reset
    # the gateway has not applied the reset yet: its samples report the tuned gains
    gw.send("AUTO", {"t": 171.0, "e": 2.0, "kp": step.kp, "ki": step.ki})
    gw.send("FRZ", {"t": 1.0, "e": 2.0, "kp": 0.7, "ki": 0.02})  # an operator's gains
    received(tuner, 173)
    assert (tuner.view("AUTO").kp, tuner.view("AUTO").ki) == (0.5, 0.01)
    assert [e.reason for e in tuner.history("AUTO", 0, 10).items][:2] == ["reset", "agent"]
    gw.send("AUTO", {"t": 172.0, "e": 2.0, "kp": 0.5, "ki": 0.01})  # now applied
    received(tuner, 174)
    assert not tuner.table.pending[tuner.table.slot("AUTO")]

    # a frozen loop gets no gains: the reset restarts its agent state, the gains stay
    view = tuner.reset("FRZ")
    assert (view.kp, view.ki, view.seq, view.hidden_norm) == (0.7, 0.02, 0, 0.0)
    gw.send("FRZ", {"t": 2.0, "e": 2.0, "kp": 0.7, "ki": 0.02})
    received(tuner, 175)
    tuner.reset("AUTO")  # the control: on the same path, after anything of FRZ's
    control = gw.next_gains()
    assert (control.loop_id, control.reason) == ("AUTO", UpdateReason.reset), "FRZ got gains"
    reset, adopted = tuner.history("FRZ", 0, 10).items[:2]
    assert (reset.reason, reset.kp_old, reset.kp_new, adopted.reason) == (
        "reset",
        0.7,
        0.7,
        "adopted",
    )


def test_state_queryable_wildcard_unknown_and_liveliness(bus):
    tuner, gw = bus
    for loop_id in ("A", "B"):
        tuner.register(LoopConfig(**loop_body(loop_id)))
    ok, err = gw.state("nope")
    assert not ok and err == {"v": 1, "loop_id": "nope", "error": "unknown loop"}
    replies = list(gw.session.get(gw.keys.all_states, timeout=5.0))
    states = sorted(json.loads(r.ok.payload.to_bytes())["loop_id"] for r in replies)
    assert states == ["A", "B"]

    events = queue.SimpleQueue()
    watcher = gw.session.liveliness().declare_subscriber(
        gw.keys.all_tuners, lambda s: events.put((s.kind, str(s.key_expr))), history=True
    )
    try:
        assert events.get(timeout=5) == (zenoh.SampleKind.PUT, "pitune/tuners/test-tuner")
        tuner.stop()
        assert events.get(timeout=5) == (zenoh.SampleKind.DELETE, "pitune/tuners/test-tuner")
    finally:
        watcher.undeclare()


BAD = [
    (b'{"t": 1, "e":', RejectReason.malformed_json),
    (b'{"t": 1, "e": "x"}', RejectReason.schema),
    (b'{"t": 1, "e": NaN}', RejectReason.non_finite),
    (b'{"t": 1, "e": 1e300}', RejectReason.out_of_range),
    (b'{"v": 9, "t": 1, "e": 1}', RejectReason.unsupported_version),
    (b'{"t": 50, "e": 1}', RejectReason.duplicate),
    (b'{"t": 10, "e": 1}', RejectReason.out_of_order),
    (b'{"t": 60, "e": 5000}', RejectReason.out_of_range),  # 500 agent units of error
]


def test_bad_input_is_counted_by_reason_and_changes_nothing(bus):
    tuner, gw = bus
    for loop_id in ("LIC-101", "OTHER"):
        tuner.register(LoopConfig(**loop_body(loop_id)))
        gw.send(loop_id, {"t": 50.0, "e": 1.0})
    received(tuner, 2)
    before = tuner.view("LIC-101")
    for payload, _ in BAD:
        gw.send("LIC-101", payload)
    gw.send("UNKNOWN", {"t": 1.0, "e": 1.0})
    gw.session.put(gw.keys.batch, b'{"samples": [{"loop_id": "OTHER", "t": 51, "e": "no"}]}')
    received(tuner, 2 + len(BAD) + 2)
    expected = {reason: 0 for reason in RejectReason}
    for _, reason in BAD:
        expected[reason] += 1
    expected[RejectReason.unknown_loop] += 1
    expected[RejectReason.schema] += 1
    counted = {
        r: tuner.metrics.value("pitune_samples_rejected_total", reason=r.value)
        for r in RejectReason
    }
    assert counted == expected
    after = tuner.view("LIC-101")
    assert after.counters.rejected == len(BAD)
    # nothing but the counters and the record of the last refusal (the last bad sample's)
    # and the loop's counts by reason, which split its rejected counter
    assert after.refused.reason == BAD[-1][1] and before.refused is None
    assert before.refused_counts == {}
    assert after.refused_counts == dict(Counter(reason for _, reason in BAD))
    assert sum(after.refused_counts.values()) == after.counters.rejected
    moved = {"counters", "refused", "refused_counts"}
    assert after.model_dump(exclude=moved) == before.model_dump(exclude=moved)
    assert tuner.view("OTHER").counters.rejected == 1
    assert tuner.view("OTHER").refused_counts == {RejectReason.schema: 1}


def test_a_flood_on_one_loop_leaves_the_others_alone(tmp_path):
    with Tuner(tuner_settings(tmp_path, max_sample_rate_hz=20.0)) as tuner:
        gw = connected_gateway(tuner.settings)
        try:
            for loop_id in ("FLOOD", "CALM"):
                tuner.register(LoopConfig(**loop_body(loop_id)))
            for i in range(300):
                gw.send("FLOOD", {"t": float(i), "e": 1.0})
                if i % 30 == 0:
                    gw.send("CALM", {"t": float(i), "e": 1.0})
            received(tuner, 310)
            flood, calm = tuner.view("FLOOD").counters, tuner.view("CALM").counters
            assert calm.samples == 10 and calm.rejected == 0
            assert flood.samples < 100 and flood.samples + flood.rejected == 300
            rejected = tuner.metrics.value("pitune_samples_rejected_total", reason="flood")
            assert rejected == flood.rejected
        finally:
            gw.close()


json_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.text(max_size=5),
    st.floats(allow_nan=True, allow_infinity=True),
)  # fmt: skip
field_values = st.one_of(json_scalars, st.lists(json_scalars, max_size=3))
sample_like = st.fixed_dictionaries(
    {},
    optional={
        k: field_values for k in ("v", "t", "e", "sp", "pv", "kp", "ki", "auto", "saturated")
    },
)
payloads = st.one_of(
    st.binary(max_size=64),
    sample_like.map(lambda d: json.dumps(d).encode()),  # NaN/Infinity literals included
    st.recursive(json_scalars, lambda c: st.lists(c) | st.dictionaries(st.text(), c), max_leaves=8)
    .map(lambda v: json.dumps(v).encode()),
)  # fmt: skip


def test_random_payloads_never_hurt_the_daemon(bus):
    tuner, gw = bus
    for loop_id in ("FUZZ", "CONTROL"):
        tuner.register(LoopConfig(**loop_body(loop_id)))
    sent = 0

    @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
    @given(payload=payloads, loop_id=st.sampled_from(["FUZZ", "FUZZ", "GHOST"]))
    def throw(payload, loop_id):
        nonlocal sent
        gw.send(loop_id, payload)
        sent += 1

    throw()
    for i in range(170):  # a clean stream on another loop, through one RL step
        gw.send("CONTROL", {"t": float(i), "e": 1.0})
    received(tuner, sent + 170)
    assert tuner.alive and tuner.ready
    control = tuner.view("CONTROL")
    assert control.counters.samples == 170 and control.counters.rejected == 0
    assert control.counters.steps == 1
    gains = [gw.next_gains() for _ in range(control.counters.steps)]
    assert all(isinstance(g, GainsMessage) and g.loop_id == "CONTROL" for g in gains)
    fuzz = tuner.view("FUZZ")
    assert all(math.isfinite(x) for x in (fuzz.kp, fuzz.ki, fuzz.int_e, fuzz.hidden_norm))
    g = fuzz.config.guard
    assert g.kp_min <= fuzz.kp <= g.kp_max and g.ki_min <= fuzz.ki <= g.ki_max


def test_loops_of_a_gateway_get_their_gains_in_one_batch(bus):
    """Loops registered with a gateway: one GainsBatch per step batch on the gateway's key,
    nothing on their per-loop keys; the other loops keep their own messages."""
    tuner, gw = bus
    batches = queue.SimpleQueue()
    sub = gw.session.declare_subscriber(
        gw.keys.gateway_gains("gw-1"), lambda s: batches.put(s.payload.to_bytes())
    )
    try:
        fronted = [f"B{i}" for i in range(4)]
        tuner.register_many(
            [LoopConfig(**loop_body(i, sample_period_s=165.0, gateway="gw-1")) for i in fronted]
        )
        tuner.register(LoopConfig(**loop_body("SOLO", sample_period_s=165.0)))
        for t in (0.0, 165.0):
            batch = {"samples": [{"loop_id": i, "t": t, "e": 0.5} for i in [*fronted, "SOLO"]]}
            gw.session.put(gw.keys.batch, json.dumps(batch).encode())
        message = GainsBatch.model_validate_json(batches.get(timeout=5))
        assert sorted(g.loop_id for g in message.gains) == fronted
        assert {(g.seq, g.t, g.reason, g.instance_id) for g in message.gains} == {
            (1, 165.0, UpdateReason.agent, "test-tuner")
        }
        assert gw.next_gains().loop_id == "SOLO"
        tuner.reset("SOLO")  # the control: on the same path, after the step's messages
        assert gw.next_gains().reason is UpdateReason.reset, "fronted loops got messages"
        assert tuner.metrics.value("pitune_inference_batch_loops_sum") == 5  # one agent call

        # a patch to null sends the loop's gains one by one again, and is audited
        tuner.patch("B0", LoopPatch.model_validate({"gateway": None}))
        tuner.reset("B0")
        tuner.reset("B1")
        assert gw.next_gains().loop_id == "B0"
        tuner.reset("SOLO")  # the control: after B1's reset, which goes in a batch
        assert gw.next_gains().loop_id == "SOLO", "B1's reset came on its own key"
        reset = GainsBatch.model_validate_json(batches.get(timeout=5))
        assert [(g.loop_id, g.reason) for g in reset.gains] == [("B1", UpdateReason.reset)]
        patched = tuner.history("B0", 0, 10).items[1]
        assert (patched.reason, patched.detail) == ("patched", '{"gateway":null,"actor":"api"}')
    finally:
        sub.undeclare()


def test_gains_are_published_with_block_and_high_priority(bus):
    """Never dropped under congestion (the tuner assumes auto gains applied), and ahead of
    the samples' default priority: per-loop messages and batches alike."""
    tuner, gw = bus
    qos = queue.SimpleQueue()
    subs = [
        gw.session.declare_subscriber(
            key, lambda s: qos.put((str(s.key_expr), s.congestion_control, s.priority))
        )
        for key in (gw.keys.gains("SOLO"), gw.keys.gateway_gains("gw-1"))
    ]
    try:
        tuner.register(LoopConfig(**loop_body("SOLO")))
        tuner.register(LoopConfig(**loop_body("B0", gateway="gw-1")))
        got = {}

        def published_both() -> bool:  # resets until the subscriptions have reached the tuner
            tuner.reset("SOLO")
            tuner.reset("B0")
            with contextlib.suppress(queue.Empty):
                while True:
                    key, *rest = qos.get(timeout=0.2)
                    got[key] = tuple(rest)
            return len(got) == 2

        wait_until(published_both, what="gains on both keys")
        qos_of_gains = (zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA_HIGH)
        assert got == {
            "pitune/gateways/gw-1/gains": qos_of_gains,
            "pitune/loops/SOLO/gains": qos_of_gains,
        }
    finally:
        for sub in subs:
            sub.undeclare()


def test_loop_ids_from_the_wire_cannot_forge_log_lines(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="pitune.tuner")
    forged = "X\n2030-01-01 00:00:00 INFO pitune.tuner: all good"
    with Tuner(tuner_settings(tmp_path)) as tuner:
        batch = json.dumps({"samples": [{"loop_id": forged, "t": 1.0, "e": 0.0}]}).encode()
        tuner._handle([(Kind.batch, tuner.keys.batch, batch)])
    (record,) = [r for r in caplog.records if "sample rejected" in r.getMessage()]
    assert "\n" not in record.getMessage() and repr(forged) in record.getMessage()


def test_wire_text_in_a_rejection_is_escaped_and_clipped(tmp_path, caplog):
    """A samples key's gateway chunk with a newline and a terminal escape forged a
    CRITICAL line, a 5,000-char one made a 5,137-char line, and a batch whose "v" is a
    4 MB string one 4 MB WARNING line; a loop's refused view kept any detail whole."""
    caplog.set_level(logging.WARNING, logger="pitune.tuner")
    forged = "gw\n2026-12-05 06:00:00 CRITICAL pitune.admin: guard off\x1b[2J"
    with Tuner(tuner_settings(tmp_path)) as tuner:
        tuner.metrics._rejections.interval_s = 0.0  # every line, none suppressed
        tuner.register(LoopConfig(**loop_body("L1")))
        keys = tuner.keys
        for chunk in (forged, "A" * 5000):
            tuner._handle([(Kind.batch, f"{keys.prefix}/gateways/{chunk}/samples", b"{}")])
        big = b'{"v": "' + b"X" * 4_000_000 + b'", "samples": [{}]}'
        tuner._handle([(Kind.batch, keys.batch, big)])
        wire = "Y\n" * 3000  # a detail as long as a sender likes, on a registered loop
        tuner.engine._reject(Rejection(0, "L1", RejectReason.schema, wire), 1.0)
        refused = tuner.engine.view("L1").refused
    lines = [r.getMessage() for r in caplog.records if "sample rejected" in r.getMessage()]
    assert len(lines) == 4 and tuner.engine.rejected[RejectReason.bad_key] == 2
    assert all("\n" not in m and "\x1b" not in m and len(m) < 500 for m in lines)
    assert "gw\\\\n2026" in lines[0] and "[2J" in lines[0]  # on one line, escaped
    assert "(5,055 chars)" in lines[1] and "unsupported_version" in lines[2]
    assert refused.detail == wire[:200] + "... (6,000 chars)"


# -- the state reply says what holds a loop beyond its status (protocol revision 9):
# ``hold`` (the cool-down, the model check) and ``oscillating``, as the REST loop view does
# (tests/test_status_holds.py drives the same cases through the engine alone); queried with
# ``after_t`` (the reply waits for the loop's sample at that time: no sleeps)


def state_after(gw, loop_id: str, t: float) -> dict:
    """The loop's state reply once the tuner has its sample at plant time ``t``."""
    replies = list(gw.session.get(f"{gw.keys.state(loop_id)}?after_t={t!r}", timeout=5.0))
    assert len(replies) == 1 and replies[0].ok, replies
    state = json.loads(replies[0].ok.payload.to_bytes())
    assert state["last_t"] == t, state
    return state


def register(tuner, **guard) -> None:
    tuner.register(LoopConfig(
        id="L", kp=2.5, ki=0.25, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, **guard},
    ))  # fmt: skip


def test_the_state_reply_shows_the_cooldown_after_a_rollback_until_its_end(bus):
    """An operator's raise, rolled back on demand: the status still reads ``tuning``; the
    reply's hold names the cool-down and its end (8 RL periods), and is gone after it."""
    tuner, gw = bus
    register(tuner, excitation_periods=0.0)
    gains = {"kp": 2.5, "ki": 0.25}

    def send(k: int) -> dict:
        gw.send("L", {"t": float(k), "sp": 1.0, "pv": 0.9, **gains})
        return state_after(gw, "L", float(k))

    for k in range(20):
        assert send(k)["hold"] is None
    gains["kp"] = 4.0  # the operator's raise, adopted: a change pending
    assert send(20)["hold"] is None
    view = tuner.rollback("L")
    gains["kp"] = 2.5  # the gateway applies the rollback
    until = 20.0 + 8 * view.rl_period_s
    state = send(21)
    assert state["status"] == "tuning" and state["oscillating"] is False
    hold = state["hold"]
    assert hold["guard"] == "cooldown" and hold["since_t"] is None
    assert hold["until_t"] == pytest.approx(until) and f"until t = {until:.10g}" in hold["why"]
    k = 22
    while k < until:
        assert send(k)["hold"]["guard"] == "cooldown", k
        k += 1
    assert send(k)["hold"] is None


def test_the_state_reply_names_the_plant_wide_hold_and_nothing_goes_out_while_held(bus):
    """Protocol revision 10: a held plant's loops read ``tuning`` with ``hold.guard``
    ``plant``, its why naming who, when and why; no gains message while held, and the
    steps go on after the release."""
    tuner, gw = bus
    register(tuner, excitation_periods=0.0)
    tuner.set_hold("tank farm DCS change window", actor="ui:ops")
    for k in range(60):  # a period ends at t = 55
        gw.send("L", {"t": float(k), "sp": 1.0, "pv": 0.9})
    state = state_after(gw, "L", 59.0)
    assert state["status"] == "tuning" and state["seq"] == 0
    assert state["hold"]["guard"] == "plant" and state["hold"]["since_t"] is None
    assert "set by ui:ops at " in state["hold"]["why"]
    assert "tank farm DCS change window" in state["hold"]["why"]
    assert tuner.view("L").counters.steps == 0
    tuner.release_hold(actor="ui:ops")
    for k in range(60, 120):  # the next period ends at t = 110
        gw.send("L", {"t": float(k), "sp": 1.0, "pv": 0.9})
    update = gw.next_gains()
    assert (update.t, update.seq) == (110.0, 1)
    assert state_after(gw, "L", 119.0)["hold"] is None


def test_a_loop_held_for_gains_out_of_bounds_that_oscillates_says_so_on_the_bus(bus):
    """An operator sets gains above kp_max that make the loop unstable: the status is
    ``gains_out_of_bounds`` and only ``oscillating`` tells the gateway the loop rings."""
    tuner, gw = bus
    register(tuner, kp_max=5.0)
    plant = FOPTDBatch(np.array([1.0]), np.array([10.0]), np.array([2.0]), dt=1.0,
                       max_theta=3.0, noise_std=0.01, seed=0)  # fmt: skip
    plant.reset(0.0)
    pi = PIBatch(np.array([2.5]), np.array([0.25]), dt=1.0, n=1, u_min=-100, u_max=100)
    pi.initialise(np.zeros(1))
    for k in range(880):
        if k == 700:
            pi.set_gains(np.array([8.0]), np.array([0.8]))
        y = float(plant.output()[0])
        sp = 1.0 if (k // 220) % 2 == 1 else 0.0
        u = pi.step(np.array([sp - y]))
        gw.send("L", {"t": float(k), "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                      "ki": float(pi.ki[0])})  # fmt: skip
        plant.step(u)
        if k == 699:
            calm = state_after(gw, "L", float(k))
            assert calm["oscillating"] is False and calm["status"] == "tuning"
    state = state_after(gw, "L", 879.0)
    assert state["status"] == "gains_out_of_bounds" and state["oscillating"] is True
    assert tuner.view("L").oscillating is True  # the REST view says the same
