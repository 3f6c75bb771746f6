"""A member paused past its lease (a SIGSTOP, a VM freeze) wakes, finds its leases taken,
and wins the same shards again by the hashing: it takes them again only after it has
dropped the loops it had, and loads them from the store. Its renewal pops the lost
shards at once, but their loops leave the engine at a tick; a tick that read the lost
shards before that renewal and took them again after it kept the loops from before the
pause (a takeover restores only loops not in the engine), stepped them from there under
the new lease (a CI run, session 40: 138 messages of seq 2-3 after seq 100), then
dropped them at its next tick and kept the leases, renewing them with no loop in the
engine: nobody stepped those loops again. Real PostgreSQL, real Zenoh, in-process
members; the interleaving of the two threads is made by hand.

The messages it committed before the pause and had not published yet stay unpublished
when it holds the shards again: dropped from its lanes with the loops, and checked put by
put against the lease tokens of the batch's start."""

from __future__ import annotations

import contextlib
import threading
import time

import orjson
import pytest

from service.daemon.store_pg import connect
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 3.0


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path / name, db_path=url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


def _held_by(url: str, owner: str, shards: set[str]) -> int:
    """How many of ``shards`` ``owner`` holds an unexpired lease of."""
    with connect(url) as conn:
        (n,) = conn.execute(
            "SELECT count(*) FROM leases WHERE owner = %s AND shard = ANY(%s) "
            "AND expires > clock_timestamp()",
            (owner, sorted(shards)),
        ).fetchone()
    return n


@contextlib.contextmanager
def _pair(tmp_path, url: str):
    """Two members sharing 20 loops, each owning some; (a, b, a's shards, a's loops)."""
    a = _member(tmp_path, url, "a")
    b = _member(tmp_path, url, "b", zenoh_connect=a.settings.zenoh_listen)
    try:
        a.register_many([LoopConfig(**loop_body(f"L{i:02d}")) for i in range(20)])
        wait_until(
            lambda: len(a.loop_ids()) + len(b.loop_ids()) == 20 and min(
                len(a.loop_ids()), len(b.loop_ids())) > 0,
            timeout=3 * LEASE_S,
            what="both members owning loops",
        )  # fmt: skip
        yield a, b, set(a.cluster.held), set(a.loop_ids())
    finally:
        b.stop()
        a.stop()


def _paused_and_taken_over(a: Tuner, b: Tuner, loops: set[str]) -> None:
    """a paused (no renewal, no tick; its token stays on the bus) until b has taken its
    loops and published two messages of each (reset twice)."""
    a.cluster.halt()
    wait_until(lambda: loops <= set(b.loop_ids()), timeout=3 * LEASE_S, what="b's takeover")
    for loop_id in sorted(loops):
        b.reset(loop_id, actor="operator")
        b.reset(loop_id, actor="operator")


def _released_by_b(url: str, shards: set[str]) -> None:
    """b hands back the shards a wins (it sees a live again)."""
    wait_until(lambda: _held_by(url, "b", shards) == 0, timeout=3 * LEASE_S, what="b's release")


def test_a_member_waking_takes_its_shards_again_only_with_their_stored_loops(tmp_path, pg_url):
    with _pair(tmp_path, pg_url) as (a, b, shards, loops):
        assert {a.view(i).seq for i in loops} == {0}
        _paused_and_taken_over(a, b, loops)
        assert {b.view(i).seq for i in loops} == {2}
        real_gone = a.cluster._gone

        def renewal_meanwhile(live):
            """Between the tick's reading of the lost shards and its acquisitions: the
            lease thread's renewal (the member row live again, the leases found taken),
            then b handing the shards a wins back."""
            a.cluster._gone = real_gone
            a.cluster._renew(time.monotonic())
            assert not set(a.cluster.held) & shards
            _released_by_b(pg_url, shards)
            return real_gone(live)

        a.cluster._gone = renewal_meanwhile
        a.cluster.tick()
        # not taken again while its loops from before the pause are in the engine
        assert not set(a.cluster.held) & shards and set(a.loop_ids()) == loops
        a.cluster._renew(time.monotonic())  # (the lease thread's next: a stays live)
        a.cluster.tick()  # they are dropped, then the shards taken and loaded
        # a holds its shards again, with their loops as stored: b's seq, not its own
        assert set(a.cluster.held) == shards
        assert set(a.loop_ids()) == loops
        assert {a.view(i).seq for i in loops} == {2}
        assert _held_by(pg_url, "a", shards) == len(shards)


def test_messages_of_a_lost_lease_stay_unpublished_when_the_member_takes_it_back(tmp_path, pg_url):
    """a's committed messages not out when it is paused: y's in the middle of a batch
    (its lane's thread between two puts), z's waiting in the lane. Waking, a finds the
    leases taken, drops the loops, and takes them back (b hands them over) under new
    tokens before its lane goes on: neither goes out after b's messages. Before, the
    renewal made the leases valid again and the new tokens let both through: seq 1
    after b's seq 3."""
    with _pair(tmp_path, pg_url) as (a, b, shards, loops):
        w, x, y, z = sorted(loops)[:4]
        keys = a.settings.keys
        peer = open_peer([a.settings.zenoh_listen[0], b.settings.zenoh_listen[0]])
        heard: list[tuple[str, int, int, str]] = []

        def hear(sample) -> None:
            m = orjson.loads(sample.payload.to_bytes())
            heard.append((m["loop_id"], m["seq"], m["epoch"], m["instance_id"]))

        peer.declare_subscriber(keys.all_gains, hear)
        w_put, x_out, between, go_on = (threading.Event() for _ in range(4))
        put, may_publish = a.bus.publish, a.cluster.may_publish

        def publish(key: str, payload: bytes) -> None:
            if key == keys.gains(w):  # the lane's thread held in w's put
                w_put.wait()
            put(key, payload)
            if key == keys.gains(x):
                x_out.set()

        def paused_between_puts() -> bool:
            if x_out.is_set() and not go_on.is_set():  # after x's put, before y's
                between.set()
                go_on.wait()
            return may_publish()

        a.bus.publish, a.cluster.may_publish = publish, paused_between_puts
        try:
            a.reset(w, actor="operator")
            a.reset(x, actor="operator")
            a.reset(y, actor="operator")  # x's and y's: the lane's next batch
            w_put.set()
            wait_until(between.is_set, timeout=10.0, what="the lane between x's and y's puts")
            a.reset(z, actor="operator")  # waiting in the lane
            _paused_and_taken_over(a, b, loops)
            # a wakes: its renewal finds the leases taken, its tick drops the loops; b
            # hands the shards back, and a takes them, loaded as b left them
            a.cluster._renew(time.monotonic())
            a.cluster.tick()
            _released_by_b(pg_url, shards)
            a.cluster._renew(time.monotonic())
            a.cluster.tick()
            assert set(a.cluster.held) == shards and a.view(y).seq == a.view(z).seq == 3
        finally:
            go_on.set()
        lane = a.lanes[None]
        wait_until(lambda: lane.idle, timeout=10.0, what="a's lane done")
        assert a.gains_fenced == 2  # y's and z's
        a.reset(x, actor="operator")  # out after anything a's lane sent before
        wait_until(lambda: (x, 4) in {h[:2] for h in heard}, timeout=10.0, what="x's seq 4")
        peer.close()
        late = [h for h in heard if h[0] in (y, z) and h[1] == 1 and h[3] == "a"]
        assert late == []
        top: dict[str, int] = {}
        for loop_id, seq, _, _ in heard:  # (a message sent again repeats its loop's top)
            assert seq >= top.get(loop_id, 0), (loop_id, seq, top)
            top[loop_id] = seq
