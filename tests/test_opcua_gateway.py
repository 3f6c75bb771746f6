"""The OPC UA gateway against a real asyncua server (the simulated DCS, in-process) and
real Zenoh on loopback: samples with source timestamps, the gains in force and the
update they follow (applied_seq); the write policy (auto, tuning enable, hard limits,
rate limit, seq rule); a refused write reported and adopted by a real tuner; an OPC UA
server restart mid-run; a tuner outage (gains held, bounded buffer of the newest).

Every wait is for a signal (a gateway event, a sample, a tuner view), with a deadline;
the DCS is scanned by the test (simulated time), so nothing depends on wall-clock pace.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import queue
import threading
import time

import orjson
import pytest
import zenoh

from plant_sim.config import LoopSpec, Simulation
from plant_sim.opcua_block import AUTO, MAN
from plant_sim.opcua_dcs import SimulatedDcs
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.opcua.bridge import OpcUaGateway
from service.gateways.opcua.loops import Event
from service.gateways.opcua.sitemap import SiteMap, parse_map
from service.wire.protocol import GainsMessage, Keys, LoopStatus, Mode, StateReply, encode
from service.wire.session import free_port, session_config
from tests.tuner_support import TANK_SCALING, endpoint, tuner_settings

pytestmark = pytest.mark.timeout(120)
KEYS = Keys()
LOOP = "tank1"


def tank(loop_id: str = LOOP, seed: int = 0):
    return LoopSpec("two_tank", loop_id).build(Simulation(), seed=seed, t0=0.0)


def site_for(
    dcs: SimulatedDcs, connect: list[str], limits_factor: float = 10.0, **loop: object
) -> SiteMap:
    """The DCS's map, security None (allowed), fast sampling, the bus on ``connect``."""
    data = dcs.site_map(
        limits_factor=limits_factor,
        security="None",
        allow_insecure=True,
        reconnect_min_s=0.1,
        reconnect_max_s=0.5,
        loop_defaults={"sampling_interval_ms": 10.0, "min_write_interval_s": 0.0, **loop},
    )
    data["bus"] = {"connect": connect, "batch_interval_s": 0.01}
    return parse_map(data)


def open_session(connect: list[str] | None = None, listen: list[str] | None = None):
    return zenoh.open(session_config(mode="peer", connect=connect, listen=listen))


async def until(predicate, timeout: float = 10.0, what: str = "") -> object:
    """Await ``predicate()`` truthy (checked every 5 ms), else fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what or predicate}")
        await asyncio.sleep(0.005)


@contextlib.asynccontextmanager
async def running(gateway: OpcUaGateway):
    stop = asyncio.Event()
    task = asyncio.create_task(gateway.run(stop))
    try:
        await gateway.wait_event(lambda e: e.kind == "connected")
        yield gateway
    finally:
        stop.set()
        await task


@contextlib.asynccontextmanager
async def scanning(dcs: SimulatedDcs, period: float = 0.002):
    """Scan the DCS in the background (one simulated second per scan)."""
    stop = asyncio.Event()

    async def scan() -> None:
        while not stop.is_set():
            if dcs.server is not None:
                await dcs.scan()
            await asyncio.sleep(period)

    task = asyncio.create_task(scan())
    try:
        yield
    finally:
        stop.set()
        await task


class FakeTuner:
    """A Zenoh peer posing as a tuner: liveliness token, sample batches in, gains out."""

    def __init__(self, connect: list[str] | None = None) -> None:
        """Listens on its own port, or is a client of the router at ``connect``."""
        self.endpoint = endpoint(free_port())
        if connect:
            self.session = zenoh.open(session_config(mode="client", connect=connect))
        else:
            self.session = open_session(listen=[self.endpoint])
        self.samples: queue.SimpleQueue[dict] = queue.SimpleQueue()
        self.seen: list[dict] = []
        self.state: tuple[int, float, float] | None = None
        """(seq, kp, ki) the state queryable answers for the loop."""
        self._sub = self.session.declare_subscriber(
            KEYS.batch,
            lambda s: [self.samples.put(x) for x in orjson.loads(s.payload.to_bytes())["samples"]],
        )
        self._queryable = self.session.declare_queryable(KEYS.all_states, self._on_query)
        self._token = self.session.liveliness().declare_token(KEYS.tuner("fake"))
        self._gains = self.session.declare_publisher(KEYS.gains(LOOP))
        self._matched = threading.Event()  # the gateway's gains subscriber is known here
        self._matching = self._gains.declare_matching_listener(
            lambda status: self._matched.set() if status.matching else self._matched.clear()
        )

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            if self.state is not None:
                seq, kp, ki = self.state
                reply = StateReply(loop_id=LOOP, kp=kp, ki=ki, mode=Mode.auto,
                                   status=LoopStatus.tuning, seq=seq, last_t=None,
                                   instance_id="fake")  # fmt: skip
                query.reply(KEYS.state(LOOP), encode(reply))
        finally:
            query.drop()

    def drain(self) -> list[dict]:
        while True:
            try:
                self.seen.append(self.samples.get_nowait())
            except queue.Empty:
                return self.seen

    def send(self, seq: int, kp: float, ki: float, mode: Mode = Mode.auto) -> None:
        """Publish a gains message once the gateway's subscriber is known here: a Zenoh 1.x
        publisher sends only to the subscribers it knows of, and a message put before the
        gateway's declaration reached this session was lost (CI, a loaded machine)."""
        msg = GainsMessage(loop_id=LOOP, seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=kp, ki=ki,
                           mode=mode, instance_id="fake")  # fmt: skip
        if not self._gains.matching_status.matching:
            self._matched.wait(10.0)
        self._gains.put(encode(msg))

    def close(self) -> None:
        for entity in (self._matching, self._gains, self._token, self._queryable, self._sub):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self.session.close()


def close(a, b, rel=1e-6) -> bool:
    return all(math.isclose(x, y, rel_tol=rel) for x, y in zip(a, b, strict=True))


def test_samples_and_the_write_policy():
    """Samples carry the server's source timestamps, the block's gains converted and the
    mode; gains are written only in auto, with tuning enabled, within the hard limits,
    rate-limited, once per seq; advisory updates never."""

    async def scenario() -> None:
        fake = FakeTuner()
        session = open_session(connect=[fake.endpoint])
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                site = site_for(dcs, [fake.endpoint], min_write_interval_s=0.3)
                gw = OpcUaGateway(site, session, record_events=True)
                async with running(gw):
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    kp0, ki0 = dcs.gains(LOOP)
                    scans = [(await dcs.scan())[0] for _ in range(5)]
                    await until(lambda: len(fake.drain()) >= 6, what="6 samples")
                    samples = fake.seen
                    # the initial value (last scan before start, t = -1), then scans 0..4
                    assert [s["t"] - dcs.epoch for s in samples[:6]] == [-1, 0, 1, 2, 3, 4]
                    # the block's OUT (mapped as op) as read with that PV
                    assert [s["op"] for s in samples[1:6]] == [scan.op for scan in scans]
                    assert all(close((s["kp"], s["ki"]), (kp0, ki0)) for s in samples)
                    assert samples[2]["sp"] == 60.0 and samples[2]["auto"] is True
                    assert samples[2]["saturated"] is False
                    assert not any("applied_seq" in s for s in samples)  # no update yet

                    async def outcome(seq: int) -> Event:
                        return await gw.wait_event(
                            lambda e: e.seq == seq and e.kind in ("written", "refused")
                        )

                    target = (kp0 * 1.2, ki0 * 1.1)
                    fake.send(1, *target)
                    assert (await outcome(1)).kind == "written"
                    await dcs.scan()
                    assert close(dcs.gains(LOOP), target)
                    last = lambda: fake.drain()[-1]  # noqa: E731
                    await until(lambda: close((last()["kp"], last()["ki"]), target))
                    # the gains reported are those after update 1 (protocol revision 2)
                    assert fake.seen[-1]["applied_seq"] == 1

                    lr = gw.by_id[LOOP]
                    await dcs.set_mode(LOOP, MAN)
                    await dcs.scan()
                    await until(lambda: not lr.auto, what="manual seen")
                    fake.send(2, kp0, ki0)
                    assert (await outcome(2)).detail == "manual"
                    await dcs.scan()
                    await until(lambda: fake.drain()[-1]["auto"] is False, what="auto false")
                    # refused, finished with: the block's gains (not update 2's) are reported
                    # with applied_seq 2, which the tuner adopts as the operator's choice
                    after = await until(
                        lambda: (s := fake.drain()[-1]).get("applied_seq") == 2 and s,
                        what="a sample after the refusal",
                    )
                    assert close((after["kp"], after["ki"]), target)

                    await dcs.set_mode(LOOP, AUTO)
                    await dcs.set_tuning_enable(LOOP, False)
                    await until(lambda: lr.auto and not lr.enabled, what="auto, tuning off")
                    fake.send(3, kp0, ki0)
                    assert (await outcome(3)).detail == "tuning_disabled"

                    await dcs.set_tuning_enable(LOOP, True)
                    await until(lambda: lr.enabled, what="tuning on")
                    fake.send(4, kp0 * 50, ki0)  # beyond the map's limits (x10)
                    assert (await outcome(4)).detail == "beyond_limits"
                    await dcs.scan()
                    assert close(dcs.gains(LOOP), target)  # nothing written since seq 1

                    fake.send(5, kp0, ki0)
                    fifth = await outcome(5)
                    fake.send(6, kp0 * 0.9, ki0 * 0.9)
                    sixth = await outcome(6)
                    assert fifth.kind == sixth.kind == "written"
                    assert sixth.at - fifth.at >= 0.25  # rate limit 0.3 s (write durations vary)
                    fake.send(6, kp0 * 2, ki0)  # duplicate seq: dropped by the seq rule
                    fake.send(7, kp0 * 2, ki0, mode=Mode.advisory)  # never written
                    await until(lambda: gw.stats["advisory"] == 1 and gw.bus.inbox.stale == 1)
                    await dcs.scan()
                    assert close(dcs.gains(LOOP), (kp0 * 0.9, ki0 * 0.9))
                    written = [e.seq for e in gw.history if e.kind == "written"]
                    assert written == [1, 5, 6]
                    assert gw.stats["written"] == 3
        finally:
            session.close()
            fake.close()

    asyncio.run(scenario())


def tuner_with_tank(tmp_path, dcs_gains) -> Tuner:
    tuner = Tuner(tuner_settings(tmp_path)).start()
    kp, ki = dcs_gains
    # a 10x faster model hint than the tank's: an RL step every 16.5 samples, not 165
    scaling = {**TANK_SCALING, "tau_hat": TANK_SCALING["tau_hat"] / 10}
    guard = {"excitation_periods": 0.0}
    tuner.register(
        LoopConfig(id=LOOP, kp=kp, ki=ki, sample_period_s=1.0, scaling=scaling, guard=guard)
    )
    return tuner


def test_real_tuner_refused_write_adopted_then_server_restart_loses_no_update(tmp_path):
    """With a real tuner: a write the server refuses is reported (the gains in force in
    the samples) and the tuner adopts them; writes then resume; the OPC UA server is
    restarted mid-run and the gateway reconnects, resubscribes and goes on writing
    every update exactly once, in seq order."""

    async def scenario() -> None:
        port = free_port()
        loop = tank()
        dcs = await SimulatedDcs([loop], port=port).start()
        kp0, ki0 = dcs.gains(LOOP)
        tuner = tuner_with_tank(tmp_path, (kp0, ki0))
        session = open_session(connect=tuner.settings.zenoh_listen)
        try:
            site = site_for(dcs, [], limits_factor=1000.0)  # the untrained agent roams
            gw = OpcUaGateway(site, session, record_events=True)
            async with running(gw):
                view = lambda: tuner.view(LOOP)  # noqa: E731
                written = lambda: [e.seq for e in gw.history if e.kind == "written"]  # noqa: E731
                # 1. the DCS refuses the writes: the tuner adopts the gains in force
                await dcs.lock_gains(LOOP)
                async with scanning(dcs):
                    refused = await gw.wait_event(lambda e: e.kind == "refused", timeout=60)
                    assert (refused.seq, refused.detail) == (1, "server:BadUserAccessDenied")
                    await until(
                        lambda: view().seq >= 2 and close((view().kp, view().ki), (kp0, ki0)),
                        timeout=60,
                        what="the tuner adopting the block's gains",
                    )
                    assert dcs.gains(LOOP) == (kp0, ki0) and written() == []
                    audit = tuner.history(LOOP, 0, 100).items
                    assert any(row.reason == "adopted" for row in audit)
                    # 2. writes allowed again: the next updates go through
                    await dcs.lock_gains(LOOP, False)
                    await until(lambda: len(written()) >= 2, timeout=60, what="2 writes")
                # 3. the server restarts mid-run
                await dcs.stop()
                await gw.wait_event(lambda e: e.kind == "lost")
                dcs = await SimulatedDcs([loop], port=port, epoch=dcs.epoch).start()
                await gw.wait_event(lambda e: e.kind == "connected", timeout=20)
                before = len(written())
                async with scanning(dcs):
                    await until(lambda: len(written()) >= before + 2, timeout=60, what="2 more")
                    await until(lambda: view().seq == written()[-1], what="the tuner in step")
                # every update was refused (while locked) or written, once, in seq order
                seqs = written()
                refusals = [e.seq for e in gw.history if e.kind == "refused"]
                assert refusals + seqs == list(range(1, seqs[-1] + 1))
                # an update the tuner made as the scans stopped may still be on its way: the
                # block's GAIN and RESET (read back by the gateway) come to hold the tuner's
                # gains (its PI takes them at its next scan, and the scans have stopped)
                lr = gw.by_id[LOOP]
                await until(
                    lambda: close(lr.in_force(), (view().kp, view().ki)),
                    what="the block's gains equal the tuner's",
                )
                assert gw.stats["links_lost"] == 1 and gw.stats["connects"] == 2
                assert gw.stats["samples_dropped"] == 0
        finally:
            session.close()
            tuner.stop()
            await dcs.stop()

    asyncio.run(scenario())


def test_zenoh_router_restart_buffers_samples_and_recovers_missed_gains():
    """Gateway and tuner are Zenoh clients of a router. While the router is down the
    samples are held (bounded buffer) and sent in order when the tuner's token is back;
    the gains published meanwhile are recovered by the state query, and written once."""
    router_ep = endpoint(free_port())

    def router():
        return zenoh.open(session_config(mode="router", listen=[router_ep]))

    async def scenario() -> None:
        rtr = router()
        fake = FakeTuner(connect=[router_ep])
        session = zenoh.open(session_config(mode="client", connect=[router_ep]))
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                gw = OpcUaGateway(site_for(dcs, [router_ep]), session, record_events=True)
                async with running(gw):
                    kp0, ki0 = dcs.gains(LOOP)
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    await dcs.scan()
                    fake.send(1, kp0 * 1.1, ki0)
                    assert (await gw.wait_event(lambda e: e.kind != "received")).seq == 1
                    await until(lambda: len(fake.drain()) >= 2, what="samples before")
                    rtr.close()  # the router goes down
                    await until(lambda: not gw.bus.tuner_up, what="the token gone")
                    for _ in range(5):
                        await dcs.scan()
                    await until(lambda: len(gw.outbox) == 5, what="5 samples held")
                    fake.state = (2, kp0 * 1.2, ki0 * 1.1)  # published while away: lost
                    rtr = router()  # back on the same port: both clients reconnect
                    written = await gw.wait_event(lambda e: e.kind == "written", timeout=30)
                    assert (written.seq, written.detail) == (2, "")
                    await until(lambda: len(fake.drain()) >= 7, timeout=20, what="the buffer")
                    ts = [s["t"] - dcs.epoch for s in fake.seen]
                    assert ts == sorted(set(ts)) and ts[-5:] == [1, 2, 3, 4, 5]
                    await dcs.scan()
                    assert close(dcs.gains(LOOP), (kp0 * 1.2, ki0 * 1.1))
                    assert [e.seq for e in gw.history if e.kind == "written"] == [1, 2]
                    assert gw.stats["samples_dropped"] == 0
        finally:
            session.close()
            fake.close()
            rtr.close()

    asyncio.run(scenario())


def test_a_tuner_outage_holds_the_gains_and_a_bounded_buffer_of_the_newest_samples():
    """While no tuner is up the DCS controls on with the gains in force (nothing is
    written; the PV follows its setpoint), and the gateway holds at most
    ``buffer_max_samples`` samples, the newest: older ones are dropped and counted. When a
    tuner is back the held samples go out, in order."""

    async def scenario() -> None:
        fake = FakeTuner()
        session = open_session(connect=[fake.endpoint])
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                site = site_for(dcs, [fake.endpoint])
                site.bus.buffer_max_samples = 3
                gw = OpcUaGateway(site, session, record_events=True)
                async with running(gw):
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    kp0, ki0 = dcs.gains(LOOP)
                    await until(lambda: fake.drain() and not gw.outbox, what="flushed")
                    fake._token.undeclare()  # the tuner goes away
                    await until(lambda: not gw.bus.tuner_up, what="the token gone")
                    before = gw.stats["samples"]
                    scans = []
                    for k in range(40):  # each scan's PV taken before the next
                        scans += await dcs.scan()
                        await until(lambda k=k: gw.stats["samples"] == before + k + 1)
                    assert len(gw.outbox) == 3 and gw.stats["samples_dropped"] == 37
                    # the loop ran on its own: gains untouched, the level rising to 60 cm
                    assert dcs.gains(LOOP) == (kp0, ki0) and gw.stats["written"] == 0
                    assert scans[0].sp == 60.0 and scans[-1].pv > scans[0].pv + 0.1
                    seen = len(fake.drain())
                    fake._token = fake.session.liveliness().declare_token(KEYS.tuner("fake"))
                    await until(lambda: len(fake.drain()) >= seen + 3, what="the held samples")
                    held = [s["t"] - dcs.epoch for s in fake.seen[seen:]]
                    assert held == [s.t for s in scans[-3:]]
        finally:
            session.close()
            fake.close()

    asyncio.run(scenario())
