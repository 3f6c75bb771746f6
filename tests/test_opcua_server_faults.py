"""The OPC UA gateway against servers that behave unlike the simulated DCS (a bare
asyncua server whose node types, timestamps and services the test chooses; real Zenoh
on loopback): a read-back that is not Good after a Good write, a fault of the whole
Write request, integer gain nodes, a session dropped at each write, a null source
timestamp, a source clock stepped back. None of them may stop the gateway, and none
may turn into reconnect cycles."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import Server, ua

from service.gateways.opcua.bridge import OpcUaGateway
from service.gateways.opcua.sitemap import parse_map
from service.wire.session import free_port
from tests.test_opcua_gateway import LOOP, FakeTuner, open_session, until

pytestmark = pytest.mark.timeout(120)
TYPES = {"SP": ua.VariantType.Double, "PV": ua.VariantType.Double,
         "MODE": ua.VariantType.Int32, "GAIN": ua.VariantType.Double,
         "RESET": ua.VariantType.Double, "TUNE_EN": ua.VariantType.Boolean}  # fmt: skip
INIT = {"SP": 50.0, "PV": 49.0, "MODE": 2, "GAIN": 1.0, "RESET": 2.0, "TUNE_EN": True}
"""A block in AUTO, GAIN 1 (%/%, spans 1: kp 1), RESET 2 min (ki 1/120 per s)."""


class Block:
    """A bare asyncua server with one PID block's nodes, of the given types and values."""

    def __init__(self, types=None, init=None) -> None:
        self.url = f"opc.tcp://127.0.0.1:{free_port()}/faults"
        self.types, self.init = {**TYPES, **(types or {})}, {**INIT, **(init or {})}

    async def __aenter__(self) -> Block:
        self.server = server = Server()
        await server.init()
        server.set_endpoint(self.url)
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        self.ns = await server.register_namespace("urn:pitune:faults")
        obj = await server.nodes.objects.add_object(ua.NodeId(LOOP, self.ns), LOOP)
        self.ids = {}
        for name, vtype in self.types.items():
            self.ids[name] = ua.NodeId(f"{LOOP}.{name}", self.ns)
            var = await obj.add_variable(self.ids[name], name, ua.Variant(self.init[name], vtype))
            await var.set_writable()
        await server.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await asyncio.wait_for(self.server.stop(), 10)

    async def put(self, name: str, value, ts=None, server_ts=None) -> None:
        dv = ua.DataValue(ua.Variant(value, self.types[name]), SourceTimestamp=ts,
                          ServerTimestamp=server_ts)  # fmt: skip
        await self.server.write_attribute_value(self.ids[name], dv)

    async def get(self, name: str):
        return await self.server.get_node(self.ids[name]).read_value()

    def on_write(self, hook) -> None:
        """Serve the Write service with ``hook(params, write)``, ``write()`` the server's."""
        service = self.server.iserver.attribute_service
        original = self.__dict__.setdefault("_write", service.write)

        async def write(params, user=None):
            if all(wv.NodeId.NamespaceIndex != self.ns for wv in params.NodesToWrite):
                return await original(params, user=user)  # the server's own (its status)
            return await hook(params, lambda: original(params, user=user))

        service.write = write

    def site(self, endpoint: str):
        node = lambda name: f"ns={self.ns};s={LOOP}.{name}"  # noqa: E731
        return parse_map({
            "server": {"url": self.url, "security": "None", "allow_insecure": True,
                       "reconnect_min_s": 0.1, "reconnect_max_s": 0.8},
            "bus": {"connect": [endpoint], "batch_interval_s": 0.01},
            "loops": [{"id": LOOP, "sp": node("SP"), "pv": node("PV"), "mode": node("MODE"),
                       "auto_values": [2, 3], "p": node("GAIN"), "i": node("RESET"),
                       "tuning_enable": node("TUNE_EN"), "form": {"p": "gain", "i": "reset_min"},
                       "limits": {"p": [0.01, 100.0], "i": [0.01, 100.0]},
                       "sampling_interval_ms": 10.0, "min_write_interval_s": 0.0}],
        })  # fmt: skip


def _run(scenario, block: Block | None = None) -> None:
    async def main() -> None:
        fake = FakeTuner()
        session = open_session(connect=[fake.endpoint])
        try:
            async with block or Block() as dcs:
                gw = OpcUaGateway(dcs.site(fake.endpoint), session, record_events=True)
                stop = asyncio.Event()
                task = asyncio.create_task(gw.run(stop))
                try:
                    await gw.wait_event(lambda e: e.kind == "connected")
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    await scenario(dcs, gw, fake)
                    assert not task.done(), "the gateway stopped"
                finally:
                    stop.set()
                    await task
        finally:
            session.close()
            fake.close()

    asyncio.run(main())


async def _outcome(gw: OpcUaGateway, seq: int):
    kinds = ("written", "refused", "unverified", "applied_already")
    return await gw.wait_event(lambda e: e.seq == seq and e.kind in kinds)


def test_a_read_back_not_good_after_a_good_write_is_unverified_and_the_gateway_runs_on():
    async def scenario(dcs, gw, fake) -> None:
        async def uncertain(params, write):  # shown Uncertain until the controller takes it
            codes = await write()
            for wv in params.NodesToWrite:
                status = ua.StatusCode(ua.StatusCodes.UncertainInitialValue)
                await dcs.server.write_attribute_value(
                    wv.NodeId, ua.DataValue(wv.Value.Value, StatusCode=status)
                )
            return codes

        dcs.on_write(uncertain)
        fake.send(1, 1.5, 1.5 / 120.0)  # GAIN 1.5, RESET 2 min
        assert (await _outcome(gw, 1)).kind == "unverified"
        lr = gw.by_id[LOOP]
        assert gw.stats["unverified"] == 1 and gw.stats["written"] == 0
        assert lr.block_gains() is None  # not known: no gains in the samples
        await dcs.put("GAIN", 1.5)  # the controller confirms: Good again
        await dcs.put("RESET", 2.0)
        await until(lambda: lr.block_gains() == (1.5, 2.0), what="the gains notified")
        await dcs.put("PV", 49.5)
        last = await until(lambda: (s := fake.drain()) and s[-1]["pv"] == 49.5 and s[-1])
        assert (last["kp"], last["ki"]) == pytest.approx((1.5, 1.5 / 120.0))
        assert last["applied_seq"] == 1
        dcs.on_write(lambda params, write: write())
        fake.send(2, 2.0, 2.0 / 120.0)  # the gateway goes on writing
        assert (await _outcome(gw, 2)).kind == "written"

    _run(scenario)


@pytest.mark.parametrize("fault", ["BadUserAccessDenied", "BadTooManyOperations"])
def test_a_fault_of_the_whole_write_request_refuses_the_update_and_keeps_the_session(fault):
    async def scenario(dcs, gw, fake) -> None:
        async def refuse(params, write):
            raise getattr(ua.uaerrors, fault)()

        dcs.on_write(refuse)
        fake.send(1, 1.5, 1.5 / 120.0)
        event = await _outcome(gw, 1)
        assert (event.kind, event.detail) == ("refused", f"server:{fault}")
        assert gw.stats["refused_by_server"] == 1 and gw.bus.applied_seq(LOOP) == 1
        assert gw.link is not None and gw.stats["connects"] == 1
        assert "links_lost" not in gw.stats and await dcs.get("GAIN") == 1.0
        dcs.on_write(lambda params, write: write())
        fake.send(2, 1.5, 1.5 / 120.0)
        assert (await _outcome(gw, 2)).kind == "written"
        assert gw.stats["connects"] == 1 and await dcs.get("GAIN") == 1.5

    _run(scenario)


def test_integer_gain_nodes_take_integral_values_and_refuse_others():
    async def scenario(dcs, gw, fake) -> None:
        fake.send(1, 2.5, 2.5 / 180.0)  # GAIN 2.5, RESET 3 min: not an Int32
        event = await _outcome(gw, 1)
        assert (event.kind, event.detail) == ("refused", "not_integral")
        assert (await dcs.get("GAIN"), await dcs.get("RESET")) == (2, 3)
        fake.send(2, 4.0, 4.0 / 300.0)  # GAIN 4, RESET 5 min: written as Int32
        assert (await _outcome(gw, 2)).kind == "written"
        assert (await dcs.get("GAIN"), await dcs.get("RESET")) == (4, 5)
        assert gw.stats["connects"] == 1 and "links_lost" not in gw.stats

    ints = {"GAIN": ua.VariantType.Int32, "RESET": ua.VariantType.Int32}
    _run(scenario, Block(types=ints, init={"GAIN": 2, "RESET": 3}))


def test_a_session_lost_at_each_write_reconnects_with_a_growing_delay():
    """A server that drops the session at every write (here it answers the Write with
    BadSessionClosed): each reconnect waits twice as long as the one before, up to
    reconnect_max_s, instead of a reconnect (and a re-read of every node) per write."""

    async def scenario(dcs, gw, fake) -> None:
        async def drop(params, write):
            raise ua.uaerrors.BadSessionClosed()

        dcs.on_write(drop)
        fake.send(1, 1.5, 1.5 / 120.0)
        ups = [await gw.wait_event(lambda e: e.kind == "connected") for _ in range(4)]
        losses = [e for e in gw.history if e.kind == "lost"][:4]
        gaps = [up.at - lost.at for lost, up in zip(losses, ups, strict=True)]
        assert all(gap >= delay for gap, delay in zip(gaps, [0.1, 0.2, 0.4, 0.8], strict=True))
        assert gw.by_id[LOOP].pending is not None  # not known to be written: still pending

    _run(scenario)


def test_a_null_source_timestamp_falls_back_to_the_server_timestamp():
    async def scenario(dcs, gw, fake) -> None:
        null = datetime(1601, 1, 1, tzinfo=UTC)  # OPC UA's DateTime 0
        now = datetime.now(UTC).replace(microsecond=0) + timedelta(seconds=10)
        await until(lambda: gw.by_id[LOOP].replays == 0, what="the initial values")
        for k in range(3):
            await dcs.put("PV", 50.0 + k, ts=null, server_ts=now + timedelta(seconds=k))
            await until(lambda k=k: any(s["pv"] == 50.0 + k for s in fake.drain()))
        ts = [s["t"] - now.timestamp() for s in fake.seen if s["pv"] >= 50.0]
        assert ts == [0.0, 1.0, 2.0]  # not 1601 (then every later one is "not newer")
        assert gw.stats["samples"] == 4  # the initial value's and these

    _run(scenario)


def test_samples_after_the_source_clock_stepped_back_are_sent():
    """An hour-fast clock corrected: the samples after it are older than the last one
    sent, and are sent (the tuner takes 10 increasing ones for a new plant clock); only a
    repeated timestamp is not."""

    async def scenario(dcs, gw, fake) -> None:
        now = datetime.now(UTC).replace(microsecond=0)
        await until(lambda: gw.by_id[LOOP].replays == 0, what="the initial values")
        repeats = gw.stats["samples_not_newer"]  # the initial value notified after its read

        async def put(pv: float, t: timedelta) -> None:
            await dcs.put("PV", pv, ts=now + t)
            await until(lambda: any(s["pv"] == pv for s in fake.drain()), what=pv)

        await put(45.0, timedelta(hours=1))
        for k in range(12):
            await put(50.0 + k, timedelta(seconds=k))
        await dcs.put("PV", 70.0, ts=now + timedelta(seconds=11))  # the same t: not sent
        await put(71.0, timedelta(seconds=12))
        sent = [(s["t"] - now.timestamp(), s["pv"]) for s in fake.seen if s["pv"] != 49.0]
        assert sent == [(3600.0, 45.0), *((k, 50.0 + k) for k in range(12)), (12.0, 71.0)]
        assert gw.stats["samples_older"] == 1 and gw.stats["samples_not_newer"] == repeats + 1
        assert f"not newer {repeats + 1}, older 1" in gw.status_line()

    _run(scenario)
