"""Issue 18 defect 11: one stuck gateway stalls nobody else. A put to a congested link
blocks (congestion control BLOCK) until Zenoh closes the link; here the put to the stuck
gateway's key blocks until the test releases it. Meanwhile the other loops are stepped
and their gains published, and the loop table (REST, /metrics) answers at once. Nothing
is published that is not committed, and a lane holds at most one message per loop once
past its bound."""

from __future__ import annotations

import json
import threading
import time

import pytest

from service.daemon.lanes import Lane
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import connected_gateway, loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(60)
STUCK_S = 6.0


def test_a_stuck_gateway_delays_only_its_own_gains(tmp_path):
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        body = {"sample_period_s": 165.0}  # every sample ends an RL period
        tuner.register_many(
            [LoopConfig(**loop_body(f"S{i}", gateway="gw-stuck", **body)) for i in range(50)]
        )
        tuner.register(LoopConfig(**loop_body("SOLO", **body)))
        gw = connected_gateway(settings)
        stuck_key = settings.keys.gateway_gains("gw-stuck")
        release, blocked = threading.Event(), threading.Event()
        publish = tuner.bus.publish

        def congested(key: str, payload: bytes) -> None:
            if key == stuck_key:
                blocked.set()
                release.wait(STUCK_S)  # Zenoh closes a link blocked this long
            publish(key, payload)

        tuner.bus.publish = congested
        try:
            samples = [{"loop_id": f"S{i}", "t": 0.0, "e": 0.5} for i in range(50)]
            worst_gains = worst_view = 0.0
            for k in range(6):
                t = 165.0 * k
                for s in samples:
                    s["t"] = t
                gw.session.put(settings.keys.batch, _json({"samples": samples}))
                sent = time.monotonic()
                gw.send("SOLO", {"t": t, "e": 0.5})
                if k:
                    assert gw.next_gains(timeout=STUCK_S / 2).seq == k
                    worst_gains = max(worst_gains, time.monotonic() - sent)
                    # the stuck lane's thread may reach its publish just after SOLO's went out
                    assert blocked.wait(STUCK_S / 2)
                asked = time.monotonic()
                tuner.view("SOLO")
                tuner.views(0, 100)
                tuner.refresh_status_counts()
                worst_view = max(worst_view, time.monotonic() - asked)
            assert not release.is_set()
            print(f"while stuck: SOLO gains within {worst_gains:.3f} s, views {worst_view:.3f} s")
            assert worst_gains < 1.0 and worst_view < 0.5
            release.set()
            lane = tuner.lanes["gw-stuck"]
            assert lane.drain(5.0)
            assert tuner.view("S0").seq == 5  # every step committed, and published in order
        finally:
            release.set()
            gw.close()


def _json(body: dict) -> bytes:
    return json.dumps(body).encode()


def test_a_lane_past_its_bound_keeps_the_newest_message_of_each_loop():
    sent: list[list[dict]] = []
    release = threading.Event()

    def send(gateway, messages):
        release.wait(5.0)
        sent.append(messages)

    lane = Lane("gw", send, bound=10)
    try:
        lane.submit([{"loop_id": "first", "seq": 1}])
        wait_until(lambda: lane._busy, what="the lane's first put")  # now blocked
        for seq in range(1, 6):
            lane.submit([{"loop_id": f"L{i}", "seq": seq} for i in range(4)])
        assert len(lane._pending) <= 10 + 4 and lane.superseded > 0
        release.set()
        assert lane.drain(5.0)
        newest = {m["loop_id"]: m["seq"] for batch in sent for m in batch}
        assert newest == {"first": 1, **{f"L{i}": 5 for i in range(4)}}
        after_first = [m for batch in sent[1:] for m in batch]
        assert len(after_first) + lane.superseded == 20
    finally:
        release.set()
        lane.close(1.0)
