"""The OPC UA gateway's write policy where the block changed under it (a real asyncua
server, real Zenoh on loopback): judged on the block's values read just before the
write, not on the last notification (a publishing interval old); a pair the server took
only half of is undone; nothing written while no tuner is up; a restarted gateway
never writes the tuner's last gains over an operator's. And mistakes in a site map:
``[defaults]`` tables merged key by key, a node id that is not one refused with its key,
a node the server does not know costing its loop only."""

from __future__ import annotations

import asyncio

import pytest

from plant_sim.opcua_block import AUTO, MAN
from plant_sim.opcua_dcs import SimulatedDcs
from service.gateways.opcua.bridge import OpcUaGateway
from service.gateways.opcua.sitemap import MapError, parse_map
from service.wire.session import free_port
from tests.test_opcua_gateway import (
    KEYS,
    LOOP,
    FakeTuner,
    close,
    open_session,
    running,
    site_for,
    tank,
    until,
)

pytestmark = pytest.mark.timeout(120)
SLOW_MS = 2000.0
"""The loop's sampling interval: a change reaches the gateway up to 2 s late."""


def _run(scenario, **loop) -> None:
    async def main() -> None:
        fake = FakeTuner()
        session = open_session(connect=[fake.endpoint])
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                gw = OpcUaGateway(site_for(dcs, [fake.endpoint], **loop), session,
                                  record_events=True)  # fmt: skip
                async with running(gw):
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    await scenario(dcs, gw, fake)
        finally:
            session.close()
            fake.close()

    asyncio.run(main())


async def _outcome(gw: OpcUaGateway, seq: int):
    return await gw.wait_event(lambda e: e.seq == seq and e.kind in ("written", "refused"))


def test_a_switch_to_manual_or_an_operators_gain_not_yet_notified_stops_the_write():
    async def scenario(dcs, gw, fake) -> None:
        kp0, ki0 = dcs.gains(LOOP)
        lr = gw.by_id[LOOP]
        await dcs.set_mode(LOOP, MAN)
        assert lr.auto  # the notification is up to a sampling interval away
        fake.send(1, kp0 * 1.5, ki0 * 1.5)
        assert (await _outcome(gw, 1)).detail == "manual"
        assert close(dcs.gains(LOOP), (kp0, ki0))

        await dcs.set_mode(LOOP, AUTO)
        await until(lambda: lr.auto, what="auto seen")
        gain, reset = lr.block_gains()
        await dcs.set_param(LOOP, "GAIN", gain * 0.8)  # an operator's own change
        fake.send(2, kp0 * 1.2, ki0)
        assert (await _outcome(gw, 2)).detail == "stale"
        await dcs.scan()
        assert close(dcs.gains(LOOP), (kp0 * 0.8, ki0 * 0.8))  # the operator's gains kept
        assert gw.stats["written"] == 0

    _run(scenario, sampling_interval_ms=SLOW_MS)


def test_a_pair_the_server_took_half_of_is_undone():
    async def scenario(dcs, gw, fake) -> None:
        kp0, ki0 = dcs.gains(LOOP)
        block = dcs.blocks[LOOP]
        await dcs.server.get_node(block.ids["RESET"]).set_writable(False)  # locked in the DCS
        fake.send(1, kp0 * 2.0, ki0)  # a new GAIN, and a RESET that keeps ki
        event = await _outcome(gw, 1)
        assert (event.kind, event.detail) == ("refused", "server:partial:BadUserAccessDenied")
        await dcs.scan()
        assert close(dcs.gains(LOOP), (kp0, ki0))  # not kp doubled with ki doubled
        assert close(gw.by_id[LOOP].block_gains(), (await _block(dcs)))
        assert gw.stats["refused_partial"] == 1 and gw.stats["written"] == 0

    _run(scenario)


async def _block(dcs):
    ids = dcs.blocks[LOOP].ids
    return tuple([await dcs.server.get_node(ids[k]).read_value() for k in ("GAIN", "RESET")])


def test_nothing_is_written_while_no_tuner_is_up():
    async def scenario(dcs, gw, fake) -> None:
        kp0, ki0 = dcs.gains(LOOP)
        fake.send(1, kp0 * 1.1, ki0)
        assert (await _outcome(gw, 1)).kind == "written"
        fake.send(2, kp0 * 1.5, ki0 * 1.5)  # waits on the rate limit
        await gw.wait_event(lambda e: e.seq == 2 and e.kind == "received")
        fake._token.undeclare()  # the tuner is gone
        await until(lambda: not gw.bus.tuner_up, what="the tuner gone")
        later = asyncio.get_running_loop().time() + 1.5  # past the rate limit (1 s)
        await until(lambda: asyncio.get_running_loop().time() > later, what="1.5 s")
        assert gw.by_id[LOOP].pending is not None and gw.stats["written"] == 1
        await dcs.scan()
        assert close(dcs.gains(LOOP), (kp0 * 1.1, ki0))
        fake._token = fake.session.liveliness().declare_token(KEYS.tuner("fake"))
        assert (await _outcome(gw, 2)).kind == "written"  # the tuner back: its word stands

    _run(scenario, min_write_interval_s=1.0)


@pytest.mark.parametrize("tuner_first", [True, False])
def test_a_restarted_gateway_never_writes_the_tuners_last_gains_over_an_operators(tuner_first):
    """The tuner's last update (seq 5) was written before the gateway stopped, and an
    operator set other gains since. The restarted gateway learns seq 5 from the state
    query, before its first read of the block (the tuner up first) or after it (the
    session first): it cannot tell it from gains newer than the operator's, so it writes
    nothing, and reports the block's gains with applied_seq 5: the tuner adopts them.
    (A state reply after an outage, the block still as the gateway left it, is written:
    tests/test_opcua_gateway.py.)"""

    async def main() -> None:
        fake = FakeTuner()
        if not tuner_first:
            fake._token.undeclare()
        session = open_session(connect=[fake.endpoint])
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                kp0, ki0 = dcs.gains(LOOP)  # the operator's
                fake.state = (5, kp0 * 1.5, ki0 * 1.5)  # GAIN 1.5x, RESET as it was
                gw = OpcUaGateway(site_for(dcs, [fake.endpoint]), session, record_events=True)
                async with running(gw):
                    if not tuner_first:
                        await until(lambda: gw.by_id[LOOP].block_gains(), what="the first read")
                        fake._token = fake.session.liveliness().declare_token(KEYS.tuner("f"))
                    event = await gw.wait_event(lambda e: e.seq == 5 and e.kind != "received")
                    assert (event.kind, event.detail) == ("refused", "stale")
                    await dcs.scan()
                    assert close(dcs.gains(LOOP), (kp0, ki0)) and gw.stats["written"] == 0
                    sample = await until(
                        lambda: (s := fake.drain()) and s[-1].get("applied_seq") == 5 and s[-1],
                        what="a sample after seq 5",
                    )
                    assert close((sample["kp"], sample["ki"]), (kp0, ki0))
        finally:
            session.close()
            fake.close()

    asyncio.run(main())


def test_defaults_tables_are_merged_key_by_key():
    site = {
        "server": {"url": "opc.tcp://dcs:4840", "security": "None", "allow_insecure": True},
        "defaults": {
            "form": {"p": "band", "i": "reset_s"},
            "limits": {"p": [20.0, 500.0], "i": [5.0, 3000.0]},
            "registration": {"scaling": {"k_hat": 2.0, "tau_hat": 20.0},
                             "extra": {"action": "direct"}},
        },
        "loops": [{
            "id": "TIC-1", "sp": "ns=2;s=T.SP", "pv": "ns=2;s=T.PV", "p": "ns=2;s=T.PB",
            "i": "ns=2;s=T.TI", "form": {"pv_span": 120.0, "op_span": 100.0},
            "registration": {"sample_period_s": 1.0},
        }],
    }  # fmt: skip
    (loop,) = parse_map(site).loops
    assert (loop.form.p, loop.form.i, loop.form.pv_span) == ("band", "reset_s", 120.0)
    kp, ki = loop.form.to_parallel(150.0, 120.0)  # PB 150 %, TI 120 s, spans 120 / 100
    assert (kp, ki) == pytest.approx((100 / 120 / 1.5, 100 / 120 / 1.5 / 120.0))
    reg = loop.registration
    assert (reg.extra, reg.scaling.k_hat, reg.sample_period_s) == ({"action": "direct"}, 2.0, 1.0)


def test_a_node_the_server_does_not_know_costs_its_loop_not_the_others():
    async def main() -> None:
        fake = FakeTuner()
        session = open_session(connect=[fake.endpoint])
        try:
            async with SimulatedDcs([tank(), tank("tank2", seed=1)], port=free_port()) as dcs:
                site = site_for(dcs, [fake.endpoint])
                good, typo = site.loops
                typo = typo.model_copy(update={"i": typo.i + "T"})  # ...tank2.RESETT
                gw = OpcUaGateway(site.model_copy(update={"loops": [good, typo]}), session,
                                  record_events=True)  # fmt: skip
                async with running(gw):  # connected: the session is up despite the typo
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    await dcs.scan()
                    seen = await until(
                        lambda: (
                            {s["loop_id"]: s for s in fake.drain()}.keys() >= {LOOP, "tank2"}
                            and {s["loop_id"]: s for s in fake.seen}
                        ),
                        what="samples of both loops",
                    )
                    assert "kp" in seen[LOOP] and "kp" not in seen["tank2"]  # no gains known
                    kp0, ki0 = dcs.gains(LOOP)
                    fake.send(1, kp0 * 1.1, ki0)
                    assert (await _outcome(gw, 1)).kind == "written"
        finally:
            session.close()
            fake.close()

    asyncio.run(main())


def test_a_node_id_that_is_not_one_is_a_map_error_naming_its_key():
    data = {
        "server": {"url": "opc.tcp://dcs:4840", "security": "None", "allow_insecure": True},
        "loops": [{"id": "A", "sp": "ns=2;s=A.SP", "pv": "ns=2;s=A.PV", "p": "ns=2;s=A.P",
                   "i": "ns=2;i=12x", "limits": {"p": [0.1, 1.0], "i": [1.0, 10.0]}}],
    }  # fmt: skip
    with pytest.raises(MapError, match=r"loops\.0\.i: .*not an OPC UA node id"):
        parse_map(data)
