"""Backlog size against time to send it and samples rejected, measured: the OPC UA
gateway holds one loop's samples while its tuner (default flood limit) is down, then
the tuner is back on its database.

    python -m tests.backlog_drain 1000 3600 10000 36000

prints, per backlog size, the samples held, the seconds until every one was sent and
judged, the tuner's rejections by reason, the samples cut or dropped by the gateway,
and how long after the tuner was back the other loop (not scanned during the outage)
had a live sample taken; both loops are scanned at 1 s meanwhile. docs/opcua.md
(Outages) reports them; ``tests/test_opcua_backlog.py`` holds the same run, smaller.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import tempfile
import time
from pathlib import Path

from plant_sim.opcua_dcs import SimulatedDcs
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.opcua.bridge import OpcUaGateway
from service.wire.flood import MAX_SAMPLE_RATE_HZ
from service.wire.session import free_port
from tests.test_opcua_gateway import LOOP, open_session, running, scanning, site_for, tank, until
from tests.tuner_support import TANK_SCALING, endpoint, tuner_settings

OTHER = "tank2"
"""A loop not scanned during the outage: no backlog, live samples after it."""


def register(tuner: Tuner, dcs: SimulatedDcs) -> None:
    """Every block of ``dcs`` as a tank loop at 1 s samples, the excitation gate off."""
    for loop_id in dcs.blocks:
        kp, ki = dcs.gains(loop_id)
        tuner.register(
            LoopConfig(id=loop_id, kp=kp, ki=ki, sample_period_s=1.0,
                       scaling=dict(TANK_SCALING), guard={"excitation_periods": 0.0})
        )  # fmt: skip


def accepted(tuner: Tuner) -> int:
    """Samples the tuner's loops took, over its restarts (the counters are snapshotted)."""
    return sum(tuner.view(loop_id).counters.samples for loop_id in tuner.table.slot_of)


def judged(tuner: Tuner) -> int:
    return accepted(tuner) + tuner.engine.rejected.total()


async def held_through_an_outage(gw: OpcUaGateway, dcs: SimulatedDcs, tuner: Tuner, n: int):
    """Stop ``tuner`` once it judged every sample sent, and make ``n`` samples of the
    first loop (its block alone scanned) while it is down."""
    await until(lambda: not gw.outbox and judged(tuner) == gw.stats["published"])
    tuner.stop()  # snapshots every loop: counters and last_t kept
    await until(lambda: not gw.bus.tuner_up, what="the token gone")
    made = gw.stats["samples"]
    while (before := gw.stats["samples"]) - made < n:
        await dcs.blocks[LOOP].scan(dcs.server, dcs.epoch)
        # the next scan once the gateway has this one's sample (each scan moves the time)
        await until(lambda: gw.stats["samples"] > before, what="the scan's sample")  # noqa: B023


async def measure(size: int, tmp: Path) -> dict:
    gateway_ep = endpoint(free_port())
    settings = tuner_settings(
        tmp, max_sample_rate_hz=MAX_SAMPLE_RATE_HZ, zenoh_connect=[gateway_ep]
    )
    session = open_session(listen=[gateway_ep])
    tuner = None
    try:
        async with SimulatedDcs([tank(), tank(OTHER, seed=1)], port=free_port()) as dcs:
            site = site_for(dcs, [], sampling_interval_ms=1.0)
            site.bus.batch_interval_s = 0.05  # the default
            tuner = Tuner(settings).start()
            register(tuner, dcs)
            gw = OpcUaGateway(site, session, record_events=True)
            async with running(gw):
                await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                await dcs.scan()
                await held_through_an_outage(gw, dcs, tuner, size)
                tuner, held = None, len(gw.outbox)
                tuner = Tuner(settings).start()
                await until(lambda: gw.bus.tuner_up, timeout=30, what="the tuner back")
                back = time.monotonic()
                t_live = (await dcs.scan())[1].t + dcs.epoch
                other, live_s = tuner.table.slot_of[OTHER], None
                async with scanning(dcs, period=1.0):

                    def sent_and_judged() -> bool:
                        nonlocal live_s
                        if live_s is None and tuner.table.last_t[other] >= t_live:
                            live_s = time.monotonic() - back
                        return not gw.outbox and judged(tuner) >= gw.stats["published"]

                    await until(sent_and_judged, timeout=900, what="the backlog sent")
                    drain_s = time.monotonic() - back
                return {
                    "held": held,
                    "drain_s": round(drain_s, 2),
                    "other_live_s": None if live_s is None else round(live_s, 2),
                    "rejected": {k.value: v for k, v in tuner.engine.rejected.items()},
                    "cut": gw.stats["samples_cut"],
                    "dropped": gw.stats["samples_dropped"],
                }
    finally:
        if tuner is not None:
            tuner.stop()
        session.close()


def main(argv: list[str]) -> int:
    logging.disable(logging.WARNING)
    for size in map(int, argv or ["3600"]):
        with tempfile.TemporaryDirectory() as tmp:
            print(size, asyncio.run(measure(size, Path(tmp))), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
