"""Issue 18, what a gateway author needs: the store epoch orders a loop's updates across
tuner restarts (same store) and replacements (fresh store), so a late message of an old
instance is never applied over a newer one; one StateBatch per gateway on reconnect;
supervision fields in the state; ``applied_seq`` reported by the reference gateway;
``t`` of a reset."""

from __future__ import annotations

import json
import queue
import time

import pytest

from service.daemon.store import Store
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.base import GainsInbox, Gateway, Source
from service.wire.protocol import GainsMessage, Keys, Sample, StateBatch
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(120)
KEYS = Keys()


class Spy:
    """Every gains message on the bus, raw, in arrival order."""

    def __init__(self, settings) -> None:
        self.session = open_peer(settings.zenoh_listen)
        self.raw: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self.sub = self.session.declare_subscriber(
            KEYS.all_gains, lambda s: self.raw.put(s.payload.to_bytes())
        )

    def next(self) -> bytes:
        return self.raw.get(timeout=10.0)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _published(tuner: Tuner, spy: Spy, loop_id: str) -> bytes:
    """Reset ``loop_id`` until the spy hears it (subscriptions propagate): its bytes."""

    def heard():
        tuner.reset(loop_id)
        try:
            return spy.raw.get(timeout=0.3)
        except queue.Empty:
            return None

    payload = wait_until(heard, timeout=10.0, what="a gains message")
    while True:  # the last of the resets it took
        try:
            payload = spy.raw.get(timeout=0.3)
        except queue.Empty:
            return payload


def test_a_late_message_of_a_replaced_tuner_is_never_taken(tmp_path):
    db = tmp_path / "pitune.db"
    inbox = GainsInbox(loops=frozenset({"LIC-101"}))
    order = []

    def run(instance: str, db_path, listen=None):
        overrides = {"instance_id": instance, "db_path": db_path}
        if listen:
            overrides["zenoh_listen"] = listen
        return Tuner(tuner_settings(tmp_path, **overrides)).start()

    a = run("tuner-a", db)
    try:
        a.register(LoopConfig(**loop_body("LIC-101", kp=0.7)))
        spy = Spy(a.settings)
        a_first = _published(a, spy, "LIC-101")
        a_late = _published(a, spy, "LIC-101")  # delivered late, after a's successor's
        spy.close()
    finally:
        a.stop()
    b = run("tuner-b", db)  # restarted on the same store
    try:
        spy = Spy(b.settings)
        b_msg = _published(b, spy, "LIC-101")
        spy.close()
    finally:
        b.stop()
    c = run("tuner-c", tmp_path / "fresh.db")  # replaced, with a fresh store
    try:
        c.register(LoopConfig(**loop_body("LIC-101", kp=0.7)))
        spy = Spy(c.settings)
        c_msg = _published(c, spy, "LIC-101")
        spy.close()
    finally:
        c.stop()
    msgs = {n: GainsMessage.model_validate_json(p) for n, p in
            [("a1", a_first), ("a2", a_late), ("b", b_msg), ("c", c_msg)]}  # fmt: skip
    ea, eb, ec = msgs["a1"].epoch, msgs["b"].epoch, msgs["c"].epoch
    assert msgs["a2"].epoch == ea and ea < eb < ec
    assert msgs["b"].seq > msgs["a2"].seq > msgs["a1"].seq and msgs["c"].seq < msgs["b"].seq
    for name, payload in [("a1", a_first), ("b", b_msg), ("a2", a_late), ("c", c_msg),
                          ("a2", a_late), ("b", b_msg)]:  # fmt: skip
        inbox.put_raw(Source.gains, payload)
        order.append(name)
    taken = [(u.instance_id, u.seq) for u in inbox.drain()]
    assert taken == [("tuner-a", msgs["a1"].seq), ("tuner-b", msgs["b"].seq),
                     ("tuner-c", msgs["c"].seq)], (order, taken)  # fmt: skip
    assert inbox.stale == 3


def _heard(tuner: Tuner, inbox: GainsInbox) -> list:
    """Reset LIC-101 and put the gains message heard into ``inbox``: its updates."""
    spy = Spy(tuner.settings)
    try:
        inbox.put_raw(Source.gains, _published(tuner, spy, "LIC-101"))
    finally:
        spy.close()
    return inbox.drain()


def test_a_restarted_tuner_s_state_reply_does_not_undo_an_operator_s_change(tmp_path):
    """The gateway took seq 1 under the first run's epoch; the operator changed the gains
    while the tuner was down. The restarted tuner's state reply (same seq) carries the
    epoch seq 1 went out under, so the gateway drops it and keeps the operator's gains,
    which the tuner adopts from the samples (recorded under the epoch of seq 1: its
    state is still no news); its next message has the new epoch."""
    settings = tuner_settings(tmp_path)
    inbox = GainsInbox(loops=frozenset({"LIC-101"}))
    with Tuner(settings) as first:
        first.register(LoopConfig(**loop_body("LIC-101", kp=0.7)))
        (taken,) = _heard(first, inbox)
        assert taken.epoch == first.epoch
    with Tuner(settings) as again:
        assert again.epoch > taken.epoch
        session = open_peer(settings.zenoh_listen)
        try:
            wait_until(lambda: list(session.liveliness().get(KEYS.all_tuners, timeout=1.0)))
            (reply,) = session.get(KEYS.state("LIC-101"), timeout=5.0)
            inbox.put_raw(Source.state, reply.ok.payload.to_bytes())
            assert inbox.drain() == []  # the same seq under the same epoch: no news
            # the operator's gains reported: adopted (not undone), audited
            operator = {"t": 5.0, "e": 0.1, "kp": 0.4, "ki": 0.02}
            session.put(KEYS.sample("LIC-101"), json.dumps(operator).encode())
            wait_until(lambda: again.view("LIC-101").kp == 0.4, what="the adoption")
            history = again.history
            wait_until(lambda: any(e.reason == "adopted" for e in history("LIC-101", 0, 50).items),
                       what="the adoption committed")  # fmt: skip
            # its state: the same (epoch, seq), no news to write over a later change of
            # the operator's (committed under this run's epoch, it was: session 37)
            (reply,) = session.get(KEYS.state("LIC-101"), timeout=5.0)
            inbox.put_raw(Source.state, reply.ok.payload.to_bytes())
            assert inbox.drain() == []
            (reset,) = _heard(again, inbox)
            assert (reset.epoch, reset.seq) == (again.epoch, taken.seq + 1)
        finally:
            session.close()
    with Tuner(settings) as third:  # the epoch recorded with the gains, in the store
        assert third.epoch_of("LIC-101") == again.epoch


def test_epochs_increase_per_start_of_a_store(tmp_path):
    store = Store(tmp_path / "s.db")
    first = store.next_epoch(wall=1000.0)
    assert first == 1_000_000
    assert store.next_epoch(wall=10.0) == first + 1  # a clock stepped back: still above
    store.close()
    again = Store(tmp_path / "s.db")
    assert again.next_epoch(wall=10.0) == first + 2
    again.close()


def test_one_state_batch_per_gateway_with_supervision_fields(tmp_path):
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        for i in range(3):
            tuner.register(LoopConfig(**loop_body(f"B{i}", gateway="gw-1")))
        tuner.register(LoopConfig(**loop_body("OTHER", gateway="gw-2")))
        tuner.register(LoopConfig(**loop_body("SOLO")))
        for loop_id in ("B0", "B1", "SOLO"):
            tuner.reset(loop_id)
        session = open_peer(settings.zenoh_listen)
        try:
            wait_until(lambda: list(session.liveliness().get(KEYS.all_tuners, timeout=1.0)))
            session.put(KEYS.sample("B0"), json.dumps({"t": 7.0, "e": 0.1}).encode())
            wait_until(lambda: tuner.view("B0").counters.samples == 1)
            replies = list(session.get(KEYS.gateway_state("gw-1"), timeout=5.0))
            assert len(replies) == 1
            batch = StateBatch.model_validate_json(replies[0].ok.payload.to_bytes())
            assert (batch.gateway, batch.epoch) == ("gw-1", tuner.epoch)
            states = {s.loop_id: s for s in batch.states}
            assert sorted(states) == ["B0", "B1", "B2"]
            b0 = states["B0"]
            assert (b0.seq, b0.gateway, b0.rl_period_s, b0.last_t) == (1, "gw-1", 165.0, 7.0)
            assert b0.next_due_t == 7.0 + 165.0 and b0.epoch == tuner.epoch
            assert states["B2"].seq == 0 and states["B2"].next_due_t is None

            # the reference gateway: one StateBatch, the loop outside it asked alone
            gw = Gateway(session, ["B0", "B1", "B2", "SOLO"], KEYS, gateway_id="gw-1")
            try:
                got = []
                wait_until(lambda: got.extend(gw.gains()) or len(got) >= 3, what="the state")
                assert {(u.loop_id, u.source) for u in got} == {
                    ("B0", Source.state_batch), ("B1", Source.state_batch),
                    ("SOLO", Source.state),
                }  # fmt: skip
                assert gw.inbox.supervision["B2"].rl_period_s == 165.0
                assert not gw.overdue("B0", 7.0 + 165.0 * 2)
                assert gw.overdue("B0", 7.0 + 165.0 * 3.5)
            finally:
                gw.close()
        finally:
            session.close()


def test_the_reference_gateway_reports_applied_seq_and_reset_t(tmp_path):
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        tuner.register(LoopConfig(**loop_body("LIC-101")))
        session = open_peer(settings.zenoh_listen)
        samples: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        sub = session.declare_subscriber(
            KEYS.sample("LIC-101"), lambda s: samples.put(s.payload.to_bytes())
        )
        gw = Gateway(session, ["LIC-101"], KEYS)
        try:
            gw.publish("LIC-101", Sample(t=1.0, e=0.1))
            assert Sample.model_validate_json(samples.get(timeout=5)).applied_seq is None
            wait_until(lambda: tuner.view("LIC-101").counters.samples == 1)
            got = []

            def reset_heard():
                tuner.reset("LIC-101")
                got.extend(gw.gains())
                return got

            wait_until(reset_heard, what="a reset")
            update = got[-1]
            assert update.epoch == tuner.epoch
            # taken, not applied yet (a write lock, an approval window): 0, not left out,
            # so the tuner takes the old gains for lag, not for an operator's change
            gw.publish("LIC-101", Sample(t=1.5, e=0.1))
            assert Sample.model_validate_json(samples.get(timeout=5)).applied_seq == 0
            gw.applied(update)
            gw.publish("LIC-101", Sample(t=2.0, e=0.1))
            assert Sample.model_validate_json(samples.get(timeout=5)).applied_seq == update.seq
            # t of an update no sample triggered: the plant time of the newest sample
            # accepted since registration or the last reset, else none (0.0 on the wire)
            resets = [e for e in tuner.history("LIC-101", 0, 50).items if e.reason == "reset"]
            assert resets[-1].t == 1.0 and all(e.t is None for e in resets[:-1])
            assert all(u.seq != 1 or u.kp == 0.5 for u in got)
        finally:
            gw.close()
            sub.undeclare()
            session.close()


def test_an_epoch_far_ahead_of_the_clock_is_no_tuners_and_is_dropped():
    """A forged message with an epoch of 2**62 would order above every real update of
    its loop for ever; a gateway drops an epoch more than a day ahead of its clock."""
    inbox = GainsInbox(loops=frozenset({"L"}))

    def message(epoch: int, seq: int, kp: float) -> bytes:
        msg = GainsMessage(loop_id="L", seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=kp, ki=0.02,
                           mode="auto", instance_id="x", epoch=epoch)  # fmt: skip
        return msg.model_dump_json().encode()

    now_ms = int(time.time() * 1000)
    inbox.put_raw(Source.gains, message(2**62, 1, 500.0))
    inbox.put_raw(Source.gains, message(now_ms, 1, 0.5))
    inbox.put_raw(Source.gains, message(now_ms + 3_600_000, 2, 0.6))  # an hour's skew: fine
    assert [(u.seq, u.kp) for u in inbox.drain()] == [(1, 0.5), (2, 0.6)]
    assert inbox.implausible == 1


def test_the_overdue_watchdog_expects_no_update_of_a_shadow_loop(tmp_path):
    """A shadow loop steps (status ``tuning``) but gets no messages: never overdue, where
    an auto loop with the same samples is (the watchdog re-asked every few RL periods)."""
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        tuner.register(LoopConfig(**loop_body("AU", gateway="gw-1")))
        tuner.register(LoopConfig(**loop_body("SH", gateway="gw-1", mode="shadow")))
        session = open_peer(settings.zenoh_listen)
        try:
            wait_until(lambda: list(session.liveliness().get(KEYS.all_tuners, timeout=1.0)))
            for loop_id in ("AU", "SH"):
                session.put(KEYS.sample(loop_id), json.dumps({"t": 7.0, "e": 0.1}).encode())
            wait_until(lambda: all(tuner.view(i).counters.samples == 1 for i in ("AU", "SH")))
            gw = Gateway(session, ["AU", "SH"], KEYS, gateway_id="gw-1")
            try:
                wait_until(  # the state batch, taken as gains are
                    lambda: gw.gains() is not None and len(gw.inbox.supervision) == 2,
                    what="the state batch",
                )
                states = gw.inbox.supervision
                assert [(states[i].mode, states[i].status) for i in ("AU", "SH")] == [
                    ("auto", "tuning"), ("shadow", "tuning")
                ]  # fmt: skip
                late = 7.0 + 165.0 * 3.5
                assert gw.overdue("AU", late) and not gw.overdue("SH", late)
            finally:
                gw.close()
        finally:
            session.close()
