"""Samples held through a tuner outage go out paced under the tuner's flood limit
(service.gateways.backlog): before, the OPC UA gateway sent its buffer at once and the
tuner took about its limit's worth of each loop and rejected the newest as ``flood``
(2,499 of an hour's 3,600 samples of one loop).

Real parts: the simulated DCS (an asyncua server, in-process), the OPC UA gateway, the
tuner daemon restarted on its database, on loopback Zenoh. The pace itself is checked on
the backlog alone, with the clock given; ``python -m tests.backlog_drain`` measures the
run at the default flood limit (docs/opcua.md, Outages).
"""

from __future__ import annotations

import asyncio
import logging

import pytest

from plant_sim.opcua_dcs import SimulatedDcs
from service.daemon.settings import Settings
from service.daemon.tuner import Tuner
from service.gateways.backlog import CATCH_UP_S, PACE_SHARE, Backlog
from service.gateways.opcua.bridge import OpcUaGateway
from service.wire.flood import MAX_SAMPLE_RATE_HZ
from service.wire.protocol import RejectReason
from service.wire.session import free_port
from tests.backlog_drain import OTHER, accepted, held_through_an_outage, register
from tests.test_opcua_gateway import open_session, running, scanning, site_for, tank, until
from tests.tuner_support import endpoint, tuner_settings

pytestmark = pytest.mark.timeout(120)
RATE = 100.0
"""The test tuner's flood limit. At the default, 1,000, how many of a backlog sent at once
the tuner rejects depends on how fast it goes through one loop's samples (a pass each)
while its bucket refills: 735 of 3,600 on the loaded 2-core box, 2,499 on a quieter one.
At 100 the loss is certain (102 of 222 before the pace)."""
HELD = 200
LIVE_S = 0.2
"""Between two live scans: 5 samples a loop a second, under the pace (25)."""


def sample(loop_id: str, t: float) -> dict:
    return {"loop_id": loop_id, "t": t}


def test_the_tuner_and_the_gateway_share_one_flood_limit():
    """The daemon's default and the pace's come from the wire's constant (service/wire/
    flood.py, which the engine's default and bucket take too); the pace is a quarter."""
    assert Settings.model_fields["max_sample_rate_hz"].default == MAX_SAMPLE_RATE_HZ
    assert Backlog(10).rate == MAX_SAMPLE_RATE_HZ * PACE_SHARE == 250.0


def test_a_loops_backlog_goes_in_order_at_the_pace_and_other_loops_are_not_held():
    """Of 1,000 held samples of one loop, 250 go at once (the bucket full), then 250 a
    second, oldest first; another loop's samples go at the next take, in rounds of
    distinct loops, whatever the first one still holds."""
    backlog = Backlog(100_000)
    for t in range(1000):
        assert backlog.append("a", sample("a", t)) is None
    backlog.append("b", sample("b", 0))
    first = backlog.take(100.0)
    assert [s["loop_id"] for s in first[:4]] == ["a", "b", "a", "a"]
    assert [s["t"] for s in first if s["loop_id"] == "a"] == list(range(250))
    assert len(backlog) == 750 and backlog.take(100.0) == []
    backlog.append("b", sample("b", 1))
    second = backlog.take(100.5)  # half a second: 125 more of a, b's new one
    assert [s["t"] for s in second if s["loop_id"] == "a"] == list(range(250, 375))
    assert [s for s in second if s["loop_id"] == "b"] == [sample("b", 1)]
    assert len(backlog.take(200.0)) == 250  # never more than the burst at once
    assert len(backlog.take(200.4)) == 100 and len(backlog.take(202.0)) == 250
    assert len(backlog.take(210.0)) == 25 and len(backlog) == 0


def test_beyond_what_goes_in_catch_up_s_a_loop_drops_its_oldest_logged_once(caplog):
    backlog = Backlog(1_000_000, tuner_rate_hz=1.0 / PACE_SHARE)  # 1/s: 60 held at most
    assert backlog.loop_max == CATCH_UP_S == 60
    with caplog.at_level(logging.WARNING, "pitune.gateway"):
        lost = [backlog.append("a", sample("a", t)) for t in range(100)]
    assert lost == [None] * 60 + ["samples_cut"] * 40 and len(backlog) == 60
    assert len([r for r in caplog.records if "samples_cut" in r.getMessage()]) == 1
    assert [s["t"] for s in backlog.take(0.0)] == [40]  # then 1 a second, 1 at most
    assert backlog.take(0.9) == [] and [s["t"] for s in backlog.take(3.0)] == [41]


def test_beyond_max_samples_the_oldest_of_all_are_dropped():
    """The bound of all held samples drops the oldest of any loop, also once some of the
    loops' samples were sent (and after a failed send was put back)."""
    backlog = Backlog(4)
    for t in range(3):
        backlog.append("a", sample("a", t))
    backlog.append("b", sample("b", 10))
    due = backlog.take(0.0)
    assert [(s["loop_id"], s["t"]) for s in due] == [("a", 0), ("b", 10), ("a", 1), ("a", 2)]
    backlog.put_back(due[1:])  # the publisher failed after the first sample
    assert len(backlog) == 3
    lost = [backlog.append("c", sample("c", t)) for t in (20, 21, 22)]
    assert lost == [None, "samples_dropped", "samples_dropped"] and len(backlog) == 4
    left = backlog.take(10.0)
    assert sorted((s["loop_id"], s["t"]) for s in left) == [
        ("a", 2), ("c", 20), ("c", 21), ("c", 22)
    ]  # fmt: skip


def test_a_long_outage_keeps_the_backlogs_record_of_order_bounded():
    """The tuner away (no take), four loops cut at their ``loop_max`` at each sample and
    a slow one, never cut, whose samples are the oldest held. The record of each held
    sample's loop (for the oldest of all) stays within twice the samples held: before,
    it kept an entry of every sample cut (4 loops at 10 Hz: 144,000 an hour), and the
    first take after the outage went through them all. The oldest of all still go first
    beyond ``max_samples``, and each loop's take is its oldest held."""
    backlog = Backlog(300, tuner_rate_hz=1.0 / PACE_SHARE)  # 1/s: 60 held a loop
    fast = ("a", "b", "c", "d")
    for i in range(20_000):
        if i % 500 == 0:
            assert backlog.append("slow", sample("slow", i)) is None
        cut = backlog.append(fast[i % 4], sample(fast[i % 4], i))
        assert cut == (None if i < 240 else "samples_cut")
        assert len(backlog._order) <= 2 * len(backlog), i
    assert len(backlog) == 4 * 60 + 40
    for t in range(21):  # 300 held, then the oldest of all: the slow loop's
        backlog.append("new", sample("new", 20_000 + t))
    assert len(backlog) == 300 and len(backlog._order) <= 600
    due = {s["loop_id"]: s["t"] for s in backlog.take(0.0)}  # one each: a burst of 1
    assert due == {"slow": 500, "a": 19_760, "b": 19_761, "c": 19_762, "d": 19_763,
                   "new": 20_000}  # fmt: skip


def test_a_backlog_over_the_flood_limit_is_taken_whole_after_a_tuner_outage(tmp_path):
    """The tuner (run with a flood limit of 100 samples a loop per second, which the
    map's [tuner] says too) stops; the gateway holds 200 samples of one loop, then the
    tuner is back on its database. Every sample the gateway made is taken: none rejected
    (before, all but about 110 as ``flood``), so none out of order either: the first
    loop's live samples follow its backlog. The other loop's live samples reach the
    tuner while that backlog still drains, at the pace: 25 at once, then 25 a second."""
    gateway_ep = endpoint(free_port())
    settings = tuner_settings(tmp_path, max_sample_rate_hz=RATE, zenoh_connect=[gateway_ep])
    pace = RATE * PACE_SHARE

    async def scenario() -> None:
        session = open_session(listen=[gateway_ep])
        tuner = None
        try:
            async with SimulatedDcs([tank(), tank(OTHER, seed=1)], port=free_port()) as dcs:
                site = site_for(dcs, [], sampling_interval_ms=1.0)
                site.tuner.max_sample_rate_hz = RATE
                tuner = Tuner(settings).start()
                register(tuner, dcs)
                gw = OpcUaGateway(site, session, record_events=True)
                async with running(gw):
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    async with scanning(dcs, period=LIVE_S):
                        await until(lambda: accepted(tuner) >= 10, what="samples taken")
                    await held_through_an_outage(gw, dcs, tuner, HELD)
                    tuner = None
                    held = len(gw.outbox)
                    tuner = Tuner(settings).start()
                    await until(lambda: gw.bus.tuner_up, timeout=20, what="the tuner back")
                    back = asyncio.get_running_loop().time()
                    other = tuner.table.slot_of[OTHER]
                    t_live = (await dcs.scan())[1].t + dcs.epoch
                    async with scanning(dcs, period=LIVE_S):
                        # the other loop's live samples come through while the first
                        # loop's backlog still drains (about 9 s)
                        await until(lambda: tuner.table.last_t[other] >= t_live,
                                    what="the other loop's live sample")  # fmt: skip
                        still_held = len(gw.outbox)
                        await until(lambda: not gw.outbox, timeout=60, what="the drain")
                    drained = asyncio.get_running_loop().time() - back
                    stats, rejected = gw.stats, tuner.engine.rejected

                    def settled():  # every sample the gateway made sent, and judged
                        sent, taken = stats["published"], accepted(tuner)
                        done = sent == stats["samples"] and taken + rejected.total() == sent
                        return done and not gw.outbox and (sent, taken)

                    sent, taken = await until(settled, timeout=30, what="the tuner's count")
                    assert rejected[RejectReason.flood] == 0
                    assert dict(rejected) == {} and taken == sent
                    assert stats["samples_dropped"] == stats["samples_cut"] == 0
                    assert still_held > held / 2
                    # the pace: 25 at once, then 25 a second, less the live ones (5/s)
                    assert (held - pace) / pace - 0.5 < drained < (held - pace) / (pace - 10)
        finally:
            if tuner is not None:
                tuner.stop()
            session.close()

    asyncio.run(scenario())
