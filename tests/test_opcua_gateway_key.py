"""The OPC UA gateway with a ``gateway_id`` publishes its samples on its gateway's key
(``{prefix}/gateways/{id}/samples``, protocol revision 4), the one a per-gateway Zenoh
user may publish on (docs/deploy.md). Before, it always used ``{prefix}/samples``: under
the shipped ACL's per-gateway user every sample was dropped and no loop was tuned.

Real parts: the simulated DCS (an asyncua server, in-process), the tuner daemon, the
router of deploy/zenoh_router.py with the shipped ACL, the admin API over HTTP.
"""

from __future__ import annotations

import asyncio
import queue

import orjson
import pytest

from plant_sim.opcua_dcs import SimulatedDcs
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.opcua.bridge import OpcUaGateway
from service.gateways.opcua.sitemap import parse_map
from service.gateways.registration import RegistrationError
from service.wire.session import free_port
from tests.test_api_gate import _served
from tests.test_deploy_acl_gateways import PASSWORD, USER, per_gateway_client
from tests.test_deploy_acl_live import ZENOH, python_router
from tests.test_opcua_gateway import (
    KEYS,
    LOOP,
    FakeTuner,
    close,
    open_session,
    running,
    scanning,
    site_for,
    tank,
    until,
)
from tests.tuner_support import TANK_SCALING, loop_body, tuner_settings

pytestmark = pytest.mark.timeout(180)
GW = "gw-1"
"""The gateway id of the shipped ACL's example per-gateway user."""
FAST = {**TANK_SCALING, "tau_hat": TANK_SCALING["tau_hat"] / 10}
"""A 10x faster model hint than the tank's: an RL step every 16.5 samples, not 165."""


def test_tuned_through_the_router_as_the_per_gateway_zenoh_user(tmp_path):
    """The gateway runs as ``gateway-gw-1`` (its password added to the example
    credentials) through the router with the shipped ACL, the tuner as the tuner user:
    its samples reach the tuner on gw-1's samples key, none rejected, and the tuner's
    updates are written to the block, which comes to hold the tuner's gains."""
    credentials = tmp_path / "credentials.txt"
    example = (ZENOH / "credentials.txt").read_text()
    credentials.write_text(f"{example.rstrip()}\n{USER}:{PASSWORD}\n")

    async def scenario() -> None:
        async with SimulatedDcs([tank()], port=free_port()) as dcs:
            kp0, ki0 = dcs.gains(LOOP)
            with python_router(tmp_path, credentials=credentials) as router:
                settings = tuner_settings(tmp_path, zenoh_config=ZENOH / "tuner.json5",
                                          zenoh_mode="client", zenoh_connect=[router],
                                          zenoh_listen=[])  # fmt: skip
                tuner = Tuner(settings).start()
                session = None
                try:
                    tuner.register(LoopConfig(id=LOOP, kp=kp0, ki=ki0, sample_period_s=1.0,
                                              scaling=FAST, gateway=GW,
                                              guard={"excitation_periods": 0.0}))  # fmt: skip
                    session = per_gateway_client(router)
                    site = site_for(dcs, [], limits_factor=1000.0)  # the untrained agent roams
                    site.bus.gateway_id = GW
                    gw = OpcUaGateway(site, session, record_events=True)
                    view = lambda: tuner.view(LOOP)  # noqa: E731
                    async with running(gw):
                        async with scanning(dcs):
                            first = await gw.wait_event(lambda e: e.kind == "written", timeout=60)
                            await until(lambda: view().seq >= first.seq + 2, timeout=60,
                                        what="two more updates")  # fmt: skip
                        # the scans stopped: an update still on its way is written, then
                        # the block (as read back) holds the tuner's gains
                        lr = gw.by_id[LOOP]
                        await until(lambda: close(lr.in_force(), (view().kp, view().ki)),
                                    what="the block's gains equal the tuner's")  # fmt: skip
                    assert view().counters.samples > 30 and view().counters.rejected == 0
                    written = [e.seq for e in gw.history if e.kind == "written"]
                    assert written[0] == 1 and len(written) >= 3
                    assert gw.stats["samples_dropped"] == 0
                finally:
                    if session is not None:
                        session.close()
                    tuner.stop()

    asyncio.run(scenario())


def test_samples_wait_in_the_buffer_until_a_tuner_subscribes_to_the_gateways_key():
    """A cluster between two owners of the gateway: a tuner's token is up but no member
    subscribes to gw-1's samples key yet. The samples stay in the buffer, none published
    (Zenoh would drop them on this side), and the status line says why; once a
    subscriber comes, every one of them arrives there, in order, and none on
    ``pitune/samples``."""

    async def scenario() -> None:
        fake = FakeTuner()  # a token and pitune/samples, not gw-1's key
        session = open_session(connect=[fake.endpoint])
        got: queue.SimpleQueue[dict] = queue.SimpleQueue()
        sub = None
        try:
            async with SimulatedDcs([tank()], port=free_port()) as dcs:
                site = site_for(dcs, [fake.endpoint])
                site.bus.gateway_id = GW
                gw = OpcUaGateway(site, session, record_events=True)
                async with running(gw):
                    await until(lambda: gw.bus.tuner_up, what="the tuner's token")
                    for k in range(5):  # each scan's PV taken before the next
                        await dcs.scan()
                        await until(lambda k=k: gw.stats["samples"] == k + 2)  # + the read
                    assert gw.stats["published"] == 0 and len(gw.outbox) == 6
                    assert f"tuner up, none subscribed to {KEYS.gateway_samples(GW)}" in (
                        gw.status_line()
                    )
                    sub = fake.session.declare_subscriber(
                        KEYS.gateway_samples(GW),
                        lambda s: [got.put(x) for x in orjson.loads(s.payload.to_bytes())["samples"]],  # noqa: E501
                    )  # fmt: skip
                    seen = [await asyncio.to_thread(got.get, timeout=10.0) for _ in range(6)]
                    assert [s["t"] - dcs.epoch for s in seen] == [-1, 0, 1, 2, 3, 4]
                    assert gw.stats["published"] == 6 and not gw.outbox
                    assert "tuner up;" in gw.status_line()
                    assert fake.drain() == [] and gw.stats["samples_dropped"] == 0
        finally:
            if sub is not None:
                sub.undeclare()
            session.close()
            fake.close()

    asyncio.run(scenario())


def test_a_loop_registered_without_the_gateway_id_stops_the_gateway_at_start(tmp_path):
    """The map's tank1 is registered by the gateway (with gw-1), tank2 was registered by
    an admin without a gateway: its samples on gw-1's key would all be rejected
    (wrong_gateway). The gateway refuses to start, naming tank2 and the remedies, and
    changes nothing of tank2. With ``shared_samples_key`` it runs and both loops'
    samples are taken on ``pitune/samples``; with tank2 registered again with gw-1 it
    runs on gw-1's key (tank1's 409 and tank2's GET both name gw-1)."""

    async def scenario() -> None:
        async with SimulatedDcs([tank("tank1"), tank("tank2", seed=1)], port=free_port()) as dcs:
            with _served(tmp_path) as (tuner, port):
                tuner.register(LoopConfig(**loop_body("tank2")))
                data = dcs.site_map(
                    security="None", allow_insecure=True,
                    registration={"tank1": {"scaling": TANK_SCALING, "sample_period_s": 1.0}},
                    loop_defaults={"sampling_interval_ms": 10.0},
                )  # fmt: skip
                data["bus"] = {"gateway_id": GW, "batch_interval_s": 0.01}
                data["tuner"] = {"register_url": f"http://127.0.0.1:{port}", "timeout_s": 10.0}
                session = open_session(connect=tuner.settings.zenoh_listen)
                try:
                    gw = OpcUaGateway(parse_map(data), session)
                    with pytest.raises(RegistrationError) as refused:
                        await asyncio.wait_for(gw.run(asyncio.Event()), 30.0)
                    assert str(refused.value).startswith(
                        "1 loop(s) of the map registered without this gateway's id 'gw-1': "
                        "tank2 (no gateway). The gateway publishes the samples on "
                        "pitune/gateways/gw-1/samples, where the tuner rejects theirs "
                        "(wrong_gateway)"
                    ), refused.value
                    assert "shared_samples_key = true" in str(refused.value)
                    assert tuner.view("tank1").config.gateway == GW
                    assert tuner.view("tank2").config.gateway is None
                    assert tuner.view("tank2").counters.samples == 0

                    async def taken(site_data: dict) -> None:
                        gw = OpcUaGateway(parse_map(site_data), session, record_events=True)
                        before = {i: tuner.view(i).counters.samples for i in ("tank1", "tank2")}
                        async with running(gw), scanning(dcs):
                            await until(lambda: all(tuner.view(i).counters.samples > n + 3
                                                    for i, n in before.items()),
                                        timeout=30, what="both loops' samples")  # fmt: skip
                        assert tuner.metrics.value("pitune_samples_rejected_total",
                                                   reason="wrong_gateway") == 0  # fmt: skip

                    shared = {**data, "bus": {**data["bus"], "shared_samples_key": True}}
                    await taken(shared)
                    tuner.delete("tank2")
                    tuner.register(LoopConfig(**loop_body("tank2", gateway=GW)))
                    await taken(data)
                finally:
                    session.close()

    asyncio.run(scenario())
