"""Issue 18 defect 6 and 12: every received sample ends in exactly one counter (accepted:
the loops' ``samples``; rejected: by reason), at every moment a reader can see
``pitune_samples_received_total``, including messages the bus callback drops unread
(inbox full in messages or bytes, over MAX_MESSAGE_BYTES); a dropped query is no sample.
Driven through ``Tuner._handle`` and the bus callbacks, no network."""

from __future__ import annotations

import json
import random
import threading
import time

import pytest
import zenoh

from service.daemon.bus import Bus, Inbox, Kind
from service.daemon.store import Store
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.wire.protocol import MAX_MESSAGE_BYTES, RejectReason
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(120)
IDS = ["A", "B", "C", "D"]


class _Sink:
    """Stands in for the bus: publishing goes nowhere."""

    def publish(self, key: str, payload: bytes) -> None:
        pass

    connected = True
    is_open = True


@pytest.fixture
def tuner(tmp_path):
    t = Tuner(tuner_settings(tmp_path))
    t.store = Store(t.settings.db_path)
    t.epoch = t.store.next_epoch(0.0)
    t.bus = _Sink()
    for loop_id in IDS:
        t.register(LoopConfig(**loop_body(loop_id)))
    yield t
    t.store.close()


def _counts(t: Tuner) -> tuple[float, float, float]:
    received = t.metrics.value("pitune_samples_received_total")
    rejected = sum(
        t.metrics.value("pitune_samples_rejected_total", reason=r.value) for r in RejectReason
    )
    accepted = float(sum(t.table.n_samples[t.table.slot(i)] for i in IDS))
    return received, rejected, accepted


class _Fuzz:
    """Sample messages, mostly good, with every kind of oddity."""

    vals = [None, True, 1, "x", 1.5, float("nan"), 1e300, -1.0, [], {}, 0.5, 2.0]

    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)
        self.clock = dict.fromkeys(IDS, 0.0)

    def sample(self, loop_id: str | None = None) -> dict:
        rng = self.rng
        if rng.random() < 0.7:
            loop_id = loop_id or rng.choice(IDS)
            self.clock[loop_id] += rng.choice([1.0, 1.0, 1.0, 0.0, -3.0])
            d = {"loop_id": loop_id, "t": self.clock[loop_id], "e": rng.choice([1.0, -2.0])}
            if rng.random() < 0.2:
                d[rng.choice(["kp", "ki", "e", "auto", "v", "sp"])] = rng.choice(self.vals)
            return d
        keys = ("v", "t", "e", "sp", "pv", "kp", "ki", "auto", "saturated", "loop_id")
        return {k: rng.choice([*self.vals, *IDS, "GHOST"]) for k in keys if rng.random() < 0.6}

    def payload(self, batch: bool) -> bytes:
        rng = self.rng
        r = rng.random()
        if r < 0.05:
            return bytes(rng.randrange(256) for _ in range(rng.randrange(20)))
        if batch:
            if r < 0.1:
                return json.dumps(rng.choice([[1], {"samples": 3}, {"v": 2, "samples": [{}]}]))
            return json.dumps({"samples": [self.sample() for _ in range(rng.randrange(100))]})
        body = self.sample()
        body.pop("loop_id", None)
        return json.dumps(body).encode()

    def items(self, n: int) -> list:
        out = []
        for _ in range(n):
            if self.rng.random() < 0.7:
                loop_id = self.rng.choice([*IDS, "GHOST"])
                out.append((Kind.sample, f"pitune/loops/{loop_id}/sample", self.payload(False)))
            else:
                payload = self.payload(True)
                payload = payload if isinstance(payload, bytes) else payload.encode()
                out.append((Kind.batch, "pitune/samples", payload))
        return out


def test_received_is_never_ahead_of_the_samples_counted(tuner):
    """A reader that sees N received sees those N accepted or rejected (received is
    counted last), and at the end the three add up exactly."""
    fuzz = _Fuzz(0)
    groups = [fuzz.items(200) for _ in range(20)]
    done = threading.Event()

    def work() -> None:
        try:
            for items in groups:
                tuner._handle(items)
        finally:
            done.set()

    worker = threading.Thread(target=work)
    worker.start()
    observed, ahead = 0, []
    while not done.is_set():
        received = tuner.metrics.value("pitune_samples_received_total")
        _, rejected, accepted = _counts(tuner)  # read after received
        observed += 1
        if rejected + accepted < received:
            ahead.append((received, rejected, accepted))
        time.sleep(0.0005)
    worker.join()
    received, rejected, accepted = _counts(tuner)
    assert received > 10_000 and accepted > 1_000 and observed >= 3  # reads while it ran
    assert received == rejected + accepted
    assert not ahead, f"{len(ahead)} of {observed} reads saw samples in no counter: {ahead[:3]}"


class _FakeSample:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = zenoh.ZBytes(payload)


class _FakeQuery:
    def __init__(self, key: str) -> None:
        self.key_expr = key
        self.dropped = False

    def drop(self) -> None:
        self.dropped = True


def test_messages_dropped_by_the_callback_are_counted_once(tuner):
    """Inbox full (messages or bytes): one received, one ``overload``; over
    MAX_MESSAGE_BYTES: one received, one ``too_large``, refused before it is copied; a
    dropped state query is no sample. Then the queued ones are handled and it all adds up."""
    tuner.inbox = Inbox(max_items=5, max_bytes=4000)
    bus = Bus(tuner.settings, tuner.inbox, tuner._overload)
    on_sample, on_batch = bus._handler(Kind.sample), bus._handler(Kind.batch)
    on_query = bus._query_handler(Kind.query)
    fuzz = _Fuzz(1)
    big_batch = json.dumps({"samples": [fuzz.sample("A") for _ in range(60)]}).encode()
    assert 3000 < len(big_batch) < 4000
    on_batch(_FakeSample("pitune/samples", big_batch))  # queued: 1 item, >3000 bytes
    on_batch(_FakeSample("pitune/samples", big_batch))  # over the byte bound: dropped
    for i in range(6):  # four fit by count, two do not
        on_sample(_FakeSample("pitune/loops/B/sample", json.dumps({"t": i, "e": 1.0}).encode()))
    query = _FakeQuery("pitune/loops/A/state")
    on_query(query)
    huge = b" " * (MAX_MESSAGE_BYTES + 1)
    on_batch(_FakeSample("pitune/samples", huge))
    assert query.dropped and tuner.queries_dropped == 1
    assert tuner.metrics.value("pitune_samples_rejected_total", reason="overload") == 3
    assert tuner.metrics.value("pitune_samples_rejected_total", reason="too_large") == 1
    assert tuner.inbox.qsize() == 5 and tuner.inbox.nbytes <= 4000
    items = []
    while not tuner.inbox.empty():
        items.append(tuner.inbox.get_nowait())
    assert tuner.inbox.nbytes == 0
    tuner._handle(items)
    received, rejected, accepted = _counts(tuner)
    assert received == 60 + 4 + 3 + 1  # the queued batch's 60, 4 singles, 4 dropped unread
    assert received == rejected + accepted


def test_a_message_far_over_the_limit_is_dropped_by_zenoh_before_it_is_assembled(tmp_path):
    """Zenoh assembles a message before any callback sees it: the tuner's links take up
    to RX_MAX_BYTES, so a 48 MiB batch costs it no memory (no sample, no rejection),
    while one just over MAX_MESSAGE_BYTES still arrives and is counted too_large."""
    with Tuner(tuner_settings(tmp_path)) as tuner:
        tuner.register(LoopConfig(**loop_body("A")))
        session = open_peer(tuner.settings.zenoh_listen)
        try:
            m = tuner.metrics
            wait_until(lambda: list(session.liveliness().get("pitune/tuners/*", timeout=1.0)))

            def then_a_sample(payload: bytes, t: float) -> None:
                """``payload``, then a batch with one sample on the same key (in order):
                once that sample is counted, the payload was handled or dropped."""
                block = zenoh.CongestionControl.BLOCK  # as a gateway sends (DROP: lost)
                session.put("pitune/samples", payload, congestion_control=block)
                batch = {"samples": [{"loop_id": "A", "t": t, "e": 0.5}]}
                session.put("pitune/samples", json.dumps(batch).encode(), congestion_control=block)
                wait_until(lambda: tuner.view("A").counters.samples == t, 30.0, "the marker")

            then_a_sample(b" " * (48 << 20), 1.0)
            assert m.value("pitune_samples_rejected_total", reason="too_large") == 0
            assert m.value("pitune_samples_received_total") == 1  # the marker alone
            then_a_sample(b" " * (MAX_MESSAGE_BYTES + 1000), 2.0)
            assert m.value("pitune_samples_rejected_total", reason="too_large") == 1
        finally:
            session.close()
