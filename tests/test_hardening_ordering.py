"""Issue 18 defect 2: what a state reply reflects, tested exactly as docs/protocol.md
states it. Zenoh runs the sample subscribers and the queryable on separate threads, so a
plain query sent right after a sample may be handled before it; a query with
``after_t=<t>`` is answered only once the loop has a sample at ``t`` or later (or after
AFTER_T_WAIT_S, with ``last_t`` below ``t`` saying so). Under 10,000 samples/s of load on
other loops, 0 of 1,000 such queries are answered before their sample."""

from __future__ import annotations

import contextlib
import json
import threading
import time

import orjson
import pytest

from service.daemon.queries import AFTER_T_WAIT_S
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import connected_gateway, loop_body, open_peer, tuner_settings

pytestmark = pytest.mark.timeout(180)
LOAD_LOOPS = 100
LOAD_RATE = 10_000  # samples/s


def _state(session, key: str) -> dict:
    replies = list(session.get(key, timeout=5.0))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    return json.loads(replies[0].ok.payload.to_bytes())


def _load(settings, stop: threading.Event, sent: list[int]) -> None:
    """LOAD_RATE samples/s on LOAD_LOOPS other loops: every 50 ms a batch of 500 (five
    samples per loop, in time order)."""
    session = open_peer(settings.zenoh_listen)
    try:
        t, next_at = 0.0, time.monotonic()
        while not stop.is_set():
            samples = []
            for _ in range(5):
                t += 1.0
                samples += [{"loop_id": f"L{i}", "t": t, "e": 0.1} for i in range(LOAD_LOOPS)]
            session.put(settings.keys.batch, orjson.dumps({"samples": samples}))
            sent[0] += len(samples)
            next_at += len(samples) / LOAD_RATE
            time.sleep(max(0.0, next_at - time.monotonic()))
    finally:
        session.close()


def test_a_query_with_after_t_reflects_the_sample_sent_before_it(tmp_path):
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        tuner.register_many([LoopConfig(**loop_body(f"L{i}")) for i in range(LOAD_LOOPS)])
        tuner.register(LoopConfig(**loop_body("PROBE")))
        gw = connected_gateway(settings)
        stop, sent = threading.Event(), [0]
        load = threading.Thread(target=_load, args=(settings, stop, sent))
        load.start()
        try:
            key = settings.keys.state("PROBE")
            publisher = gw.session.declare_publisher(settings.keys.sample("PROBE"))
            start_sent, started = sent[0], time.monotonic()
            early_plain = 0
            for k in range(1, 201):  # plain queries: what is not guaranteed, measured
                publisher.put(json.dumps({"t": float(k), "e": 0.1}).encode())
                early_plain += _state(gw.session, key)["last_t"] != float(k)
            early, slow = 0, 0
            for k in range(201, 1201):
                publisher.put(json.dumps({"t": float(k), "e": 0.1}).encode())
                asked = time.monotonic()
                state = _state(gw.session, f"{key}?after_t={float(k)}")
                early += state["last_t"] is None or state["last_t"] < float(k)
                slow += time.monotonic() - asked >= AFTER_T_WAIT_S
            rate = (sent[0] - start_sent) / (time.monotonic() - started)
            publisher.undeclare()
        finally:
            stop.set()
            load.join()
            gw.close()
        print(f"load {rate:.0f} samples/s; plain queries before their sample: {early_plain}/200")
        # the guarantee is checked under whatever load a shared 2-core box sustains (the
        # generator shares the cores with the tuner and the queries); too little load
        # would make the check meaningless
        assert rate >= 0.5 * LOAD_RATE, f"load only {rate:.0f} samples/s"
        assert early == 0 and slow == 0, (early, slow)
        assert tuner.view("PROBE").counters.samples == 1200


def test_after_t_of_a_sample_that_never_comes_answers_after_the_wait(tmp_path):
    """The wait is bounded: the reply then says the sample was not handled."""
    with _probe(tmp_path) as (settings, tuner, gw):
        key = settings.keys.state("PROBE")
        asked = time.monotonic()
        state = _state(gw.session, f"{key}?after_t=6.0")
        waited = time.monotonic() - asked
        assert state["last_t"] == 5.0 and AFTER_T_WAIT_S <= waited < AFTER_T_WAIT_S + 1.0


@contextlib.contextmanager
def _probe(tmp_path):
    """A tuner with loop PROBE, its sample at t = 5 handled (an after_t query, the
    control), and a gateway peer: (settings, tuner, gateway)."""
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        tuner.register(LoopConfig(**loop_body("PROBE")))
        gw = connected_gateway(settings)
        try:
            gw.send("PROBE", {"t": 5.0, "e": 0.1})
            key = settings.keys.state("PROBE")
            assert _state(gw.session, f"{key}?after_t=5.0")["last_t"] == 5.0
            yield settings, tuner, gw
        finally:
            gw.close()


def _error(session, key: str) -> dict:
    """The one reply to ``key``, which must be an error reply (reply.err)."""
    replies = list(session.get(key, timeout=5.0))
    assert len(replies) == 1 and replies[0].err is not None, replies
    return json.loads(replies[0].err.payload.to_bytes())


def test_a_malformed_after_t_is_an_error_reply_at_once_and_ids_are_the_keys_chunk(tmp_path):
    """An after_t that is no finite number (a typo, a decimal comma, an overflow) was
    ignored and the state answered at once, as if it reflected the awaited sample; it is
    an ErrorReply now. An ErrorReply's loop_id is the key's id chunk, valid or not."""
    with _probe(tmp_path) as (settings, tuner, gw):
        key = settings.keys.state("PROBE")
        for raw in ("abc", "nan", "1e400", "5,5", "-inf"):
            asked = time.monotonic()
            error = _error(gw.session, f"{key}?after_t={raw}")
            assert time.monotonic() - asked < AFTER_T_WAIT_S
            assert error["loop_id"] == "PROBE", error
            assert error["error"].startswith(f"bad after_t: '{raw}'"), error
        unknown = _error(gw.session, settings.keys.state("NOPE"))
        assert (unknown["loop_id"], unknown["error"]) == ("NOPE", "unknown loop")
        bad_id = _error(gw.session, settings.keys.state("-x"))
        assert (bad_id["loop_id"], bad_id["error"]) == ("-x", "unknown loop")
        bad_gw = _error(gw.session, settings.keys.gateway_state("-g"))
        assert bad_gw["loop_id"] == "-g", bad_gw
        assert tuner.view("PROBE").counters.samples == 1  # nothing changed
