"""A gateway's own samples key (protocol revision 4): ``{prefix}/gateways/{gw}/samples``.

A single tuner takes it like the shared key, and rejects a loop of another gateway on
it (``wrong_gateway``); in a cluster only the member owning the gateway's shard
subscribes to it, so Zenoh routes each batch to one member instead of every batch to
every member, and the subscription follows the shard when it moves."""

from __future__ import annotations

import contextlib

import orjson
import pytest

from service.daemon.shards import shard_of
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.wire.protocol import Mode, RejectReason
from tests.tuner_support import loop_body, open_peer, subscribers, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 3.0
RECEIVED = "pitune_samples_received_total"
"""Counted after the samples' own counters (engine.received is counted before them)."""


def _batch(ids: list[str], t: float) -> bytes:
    return orjson.dumps({"v": 1, "samples": [{"loop_id": i, "t": t, "e": 0.5} for i in ids]})


def _publisher(session, key: str):
    """A publisher on ``key`` once a subscriber matches it (the tuner's reached us)."""
    pub = session.declare_publisher(key)
    wait_until(lambda: pub.matching_status.matching, timeout=10.0, what=f"a subscriber of {key}")
    return pub


def _member(tmp_path, pg_url: str, name: str, **extra) -> Tuner:
    """A started member of a cluster on ``pg_url``."""
    settings = tuner_settings(
        tmp_path, db_path=pg_url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


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
            wait_until(
                lambda: tuner.metrics.value(RECEIVED) == 2, timeout=30.0, what="both samples"
            )
            assert tuner.engine.rejected == {RejectReason.wrong_gateway: 1}
            assert tuner.table.n_samples[tuner.table.slot_of["A1"]] == 1
            # counted globally only: booked on B1, gwA could hide B1's own problems
            b1 = tuner.table.slot_of["B1"]
            assert tuner.table.n_rejected[b1] == 0 and b1 not in tuner.table.refused
            assert tuner.engine.view("B1").refused is None
            assert tuner.engine.view("B1").refused_counts == {}
            pub.undeclare()
            # a key whose gateway id is not one is not the shared key: refused whole
            bad = settings.keys.gateway_samples("g" * 70)
            session.put(bad, _batch(["A1", "B1"], 11.0))
            wait_until(lambda: tuner.metrics.value(RECEIVED) == 4, timeout=30.0, what="2 more")
            assert tuner.engine.rejected == {
                RejectReason.wrong_gateway: 1, RejectReason.bad_key: 2
            }  # fmt: skip
            assert tuner.table.n_samples[tuner.table.slot_of["B1"]] == 0
            # samples of B1 refused as they are read (a string error, a time beyond the
            # wire's bound) are B1's neither: gwA could fill its refusals (review R2: 2,000)
            bad_rows = b'{"v":1,"samples":[{"loop_id":"B1","t":12.0,"e":"x"},'
            bad_rows += b'{"loop_id":"B1","t":1e300,"e":0.1},{"loop_id":"A1","t":12.0,"e":"x"}]}'
            session.put(settings.keys.gateway_samples("gwA"), bad_rows)
            wait_until(lambda: tuner.metrics.value(RECEIVED) == 7, timeout=30.0, what="3 more")
            assert tuner.engine.view("B1").refused_counts == {}
            assert tuner.table.n_rejected[b1] == 0 and b1 not in tuner.table.refused
            assert tuner.engine.rejected[RejectReason.wrong_gateway] == 3
            # A1's own refused sample is A1's
            assert sum(tuner.engine.view("A1").refused_counts.values()) == 1
        finally:
            session.close()


def test_only_the_owner_of_a_gateway_hears_its_samples_and_the_key_follows_the_shard(
    tmp_path, pg_url
):
    gws = [f"gw{g}" for g in range(8)]
    configs = [LoopConfig(**loop_body(f"{g}-L{i}", gateway=g)) for g in gws for i in range(3)]

    a = _member(tmp_path, pg_url, "a")
    b = session = None
    try:
        a.register_many(configs)
        b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
        session = open_peer([*a.settings.zenoh_listen, *b.settings.zenoh_listen], admin=True)
        zids = {t: str(t.bus.session.info.zid()) for t in (a, b)}

        def settled() -> bool:  # b took its share; a member follows what it owns, only
            fa, fb = a.bus.followed, b.bus.followed
            owned = [{i.split("-")[0] for i in t.loop_ids()} for t in (a, b)]
            return fa and fb and fa | fb == set(gws) and owned == [fa, fb]

        def routed(owner) -> bool:  # the peer puts each gateway's samples to its owner only
            return all(
                subscribers(session, a.settings.keys.gateway_samples(g)) == {zids[owner(g)]}
                for g in gws
            )

        def received(*members: Tuner) -> float:
            return sum(t.metrics.value(RECEIVED) for t in members)

        wait_until(settled, timeout=2 * LEASE_S, what="the gateways shared out")
        pubs = {g: _publisher(session, a.settings.keys.gateway_samples(g)) for g in gws}
        owner = {g: a if g in a.bus.followed else b for g in gws}
        wait_until(lambda: routed(owner.get), timeout=10.0, what="the peer routing to owners")
        for g, pub in pubs.items():
            pub.put(_batch([f"{g}-L{i}" for i in range(3)], 10.0))
        wait_until(lambda: received(a, b) == 24, timeout=30.0, what="24 samples")
        assert a.engine.received == 3 * len(a.bus.followed)  # each batch heard once
        assert a.foreign_samples == b.foreign_samples == 0
        assert not a.engine.rejected and not b.engine.rejected
        b.stop()
        # b left: its gateways' keys are a's now, and their samples reach it
        wait_until(lambda: a.bus.followed == set(gws), timeout=LEASE_S, what="a follows all")
        wait_until(lambda: routed(lambda g: a), timeout=10.0, what="the peer routing to a")
        before = received(a)
        for g, pub in pubs.items():
            pub.put(_batch([f"{g}-L{i}" for i in range(3)], 20.0))
        wait_until(lambda: received(a) - before == 24, timeout=30.0, what="all batches at a")
        assert a.foreign_samples == 0
        assert not a.engine.rejected
        for pub in pubs.values():
            pub.undeclare()
    finally:
        if session is not None:
            session.close()
        if b is not None:
            b.stop()
        a.stop()


def test_configs_parsed_ahead_of_a_takeover_are_used_only_while_unchanged(pg_url):
    import threading

    from service.daemon.store_pg import PgStore
    from service.engine.audit import audit_row
    from service.engine.engine import TuningEngine

    store = PgStore(pg_url)
    try:
        configs = [LoopConfig(**loop_body(f"P{i}", gateway="gwP")) for i in range(3)]
        rows = [
            audit_row(c.id, 1.0, None, 0, "auto", "registered", None, (0.5, 0.01), "{}")
            for c in configs
        ]
        store.insert_loops(configs, rows, [0, 0, 0])
        engine = TuningEngine()
        for c in configs:
            engine.register(c)
        store.snapshot(engine.snapshot())
        assert store.parse_ahead(["gw:gwP"]) == 3
        ahead = store._ahead["P0"][1]
        saved = store._saved_ahead["P0"][2]
        changed = configs[1].model_copy(update={"mode": Mode.advisory})  # patched meanwhile
        with store.transaction() as db:
            db.execute(
                "UPDATE loops SET config = ? WHERE id = ?", (changed.model_dump_json(), "P1")
            )
            db.execute("UPDATE snapshots SET runtime = ? WHERE id = ?", ('{"x": 1}', "P2"))
        loaded = {s.config.id: s for s in store.load(["gw:gwP"])}
        assert loaded["P0"].config is ahead  # not parsed again
        assert loaded["P1"].config == changed  # the stored JSON changed: parsed from the row
        assert store._ahead == {}
        assert store.saved(loaded["P0"]) is saved  # the snapshot too
        assert store.saved(loaded["P2"]).runtime == {"x": 1}  # changed: parsed from the row
        store.saved(loaded["P1"])
        assert store._saved_ahead == {}
        stopped = threading.Event()
        stopped.set()  # a takeover began: nothing more is parsed
        assert store.parse_ahead(["gw:gwP"], stopped) == 0
        assert store.parse_ahead([]) == 0 and store._saved_ahead == {}
    finally:
        store.close()


def test_a_gateways_loop_is_left_to_its_owner_by_the_member_owning_its_ids_bucket(tmp_path, pg_url):
    """A member that does not hold a gateway's loop, but owns the bucket its id hashes to,
    knows the loop is the gateway's shard's: its per-loop state query gets one answer (the
    owner's, not also an 'unknown loop' error) and its per-loop samples are no
    ``unknown_loop`` rejection there (both were, for loops of gateways the other owned)."""
    gws = [f"gw{g}" for g in range(8)]
    ids = [f"{g}-L{i}" for g in gws for i in range(3)]
    with contextlib.ExitStack() as stack:  # stopped in reverse: the peer, b, a
        a = _member(tmp_path, pg_url, "a")
        stack.callback(a.stop)
        plain = [LoopConfig(**loop_body(f"S{i}")) for i in range(64)]  # buckets in use
        a.register_many([LoopConfig(**loop_body(i, gateway=i.split("-")[0])) for i in ids] + plain)
        b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
        stack.callback(b.stop)

        def shared() -> bool:  # both hold loops, each loop in one member
            held = [set(t.loop_ids()) for t in (a, b)]
            return all(held) and not held[0] & held[1] and len(held[0] | held[1]) == 88

        wait_until(shared, timeout=6 * LEASE_S, what="the loops shared out")
        holder = {i: a if i in a.loop_ids() else b for i in ids}
        other = {a: b, b: a}
        crossed = [i for i in ids if other[holder[i]].cluster.owns(shard_of(i, None))]
        assert crossed, "some loop's id bucket is owned by the member not holding it"
        session = open_peer([*a.settings.zenoh_listen, *b.settings.zenoh_listen])
        stack.callback(session.close)
        keys = a.settings.keys
        for loop_id in crossed:
            replies = list(session.get(keys.state(loop_id), timeout=5.0))
            assert [r.ok is not None for r in replies] == [True], loop_id
            assert (
                orjson.loads(replies[0].ok.payload.to_bytes())["instance_id"]
                == holder[loop_id].settings.instance_id
            )
        before = {t: t.metrics.value(RECEIVED) for t in (a, b)}
        for loop_id in crossed:
            session.put(keys.sample(loop_id), orjson.dumps({"t": 100.0, "e": 0.1}))
        wait_until(
            lambda: sum(t.metrics.value(RECEIVED) - before[t] for t in (a, b)) >= len(crossed),
            timeout=30.0,
            what="the samples taken",
        )
        assert not a.engine.rejected and not b.engine.rejected
        for loop_id in crossed:
            assert holder[loop_id].table.n_samples[holder[loop_id].table.slot_of[loop_id]] == 1
