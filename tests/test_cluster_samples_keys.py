"""A gateway's own samples key (protocol revision 4): ``{prefix}/gateways/{gw}/samples``.

A single tuner takes it like the shared key, and rejects a loop of another gateway on
it (``wrong_gateway``); in a cluster only the member owning the gateway's shard
subscribes to it, so Zenoh routes each batch to one member instead of every batch to
every member, and the subscription follows the shard when it moves."""

from __future__ import annotations

import orjson
import pytest

from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.wire.protocol import RejectReason
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 3.0


def _batch(ids: list[str], t: float) -> bytes:
    return orjson.dumps({"v": 1, "samples": [{"loop_id": i, "t": t, "e": 0.5} for i in ids]})


def _publisher(session, key: str):
    """A publisher on ``key`` once a subscriber matches it (the tuner's reached us)."""
    pub = session.declare_publisher(key)
    wait_until(lambda: pub.matching_status.matching, timeout=10.0, what=f"a subscriber of {key}")
    return pub


def test_a_single_tuner_takes_a_gateway_s_batches_and_rejects_other_loops(tmp_path):
    settings = tuner_settings(tmp_path)
    with Tuner(settings) as tuner:
        tuner.register_many(
            [LoopConfig(**loop_body("A1", gateway="gwA")), LoopConfig(**loop_body("B1"))]
        )
        session = open_peer(settings.zenoh_listen)
        try:
            pub = _publisher(session, settings.keys.gateway_samples("gwA"))
            pub.put(_batch(["A1", "B1"], 10.0))
            wait_until(lambda: tuner.engine.received == 2, what="both samples handled")
            assert tuner.engine.rejected == {RejectReason.wrong_gateway: 1}
            assert tuner.table.n_samples[tuner.table.slot_of["A1"]] == 1
            pub.undeclare()
        finally:
            session.close()


def test_only_the_owner_of_a_gateway_hears_its_samples_and_the_key_follows_the_shard(
    tmp_path, pg_url
):
    gws = [f"gw{g}" for g in range(8)]
    configs = [LoopConfig(**loop_body(f"{g}-L{i}", gateway=g)) for g in gws for i in range(3)]

    def member(name: str, **extra) -> Tuner:
        settings = tuner_settings(
            tmp_path, db_path=pg_url, instance_id=name, cluster_lease_s=LEASE_S, **extra
        )
        return Tuner(settings).start()

    a = member("a")
    b = session = None
    try:
        a.register_many(configs)
        b = member("b", zenoh_connect=a.settings.zenoh_listen)
        session = open_peer([*a.settings.zenoh_listen, *b.settings.zenoh_listen])
        wait_until(lambda: a.bus.followed and b.bus.followed, timeout=2 * LEASE_S)
        assert a.bus.followed | b.bus.followed == set(gws)
        assert not a.bus.followed & b.bus.followed
        for t in (a, b):  # a member follows exactly the gateways whose loops it has
            assert {i.split("-")[0] for i in t.loop_ids()} == t.bus.followed
        pubs = {g: _publisher(session, a.settings.keys.gateway_samples(g)) for g in gws}
        for g, pub in pubs.items():
            pub.put(_batch([f"{g}-L{i}" for i in range(3)], 10.0))
        wait_until(lambda: a.engine.received + b.engine.received == 24, what="24 samples")
        assert a.engine.received == 3 * len(a.bus.followed)  # each batch heard once
        assert a.foreign_samples == b.foreign_samples == 0
        assert not a.engine.rejected and not b.engine.rejected
        b.stop()
        # b left: its gateways' keys are a's now, and their samples reach it
        wait_until(lambda: a.bus.followed == set(gws), timeout=LEASE_S, what="a follows all")
        before = a.engine.received
        for g, pub in pubs.items():
            pub.put(_batch([f"{g}-L{i}" for i in range(3)], 20.0))
        wait_until(lambda: a.engine.received - before == 24, what="all batches at a")
        assert not a.engine.rejected
        for pub in pubs.values():
            pub.undeclare()
    finally:
        if session is not None:
            session.close()
        if b is not None:
            b.stop()
        a.stop()
