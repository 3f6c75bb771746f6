"""A member paused past its lease (a SIGSTOP, a VM freeze) wakes, finds its leases taken,
and wins the same shards again by the hashing: it takes them again only after it has
dropped the loops it had, and loads them from the store. Its renewal pops the lost
shards at once, but their loops leave the engine at a tick; a tick that read the lost
shards before that renewal and took them again after it kept the loops from before the
pause (a takeover restores only loops not in the engine), stepped them from there under
the new lease (a CI run, session 40: 138 messages of seq 2-3 after seq 100), then
dropped them at its next tick and kept the leases, renewing them with no loop in the
engine: nobody stepped those loops again. Real PostgreSQL, real Zenoh, in-process
members; the interleaving of the two threads is made by hand."""

from __future__ import annotations

import time

import pytest

from service.daemon.store_pg import connect
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

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


def test_a_member_waking_takes_its_shards_again_only_with_their_stored_loops(tmp_path, pg_url):
    a = _member(tmp_path, pg_url, "a")
    b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
    try:
        a.register_many([LoopConfig(**loop_body(f"L{i:02d}")) for i in range(20)])
        wait_until(
            lambda: len(a.loop_ids()) + len(b.loop_ids()) == 20 and min(
                len(a.loop_ids()), len(b.loop_ids())) > 0,
            timeout=3 * LEASE_S,
            what="both members owning loops",
        )  # fmt: skip
        shards, loops = set(a.cluster.held), set(a.loop_ids())
        assert {a.view(i).seq for i in loops} == {0}
        a.cluster.halt()  # the pause: no renewal, no tick (its token stays on the bus)
        wait_until(lambda: loops <= set(b.loop_ids()), timeout=3 * LEASE_S, what="b's takeover")
        for loop_id in sorted(loops):  # the new owner's messages: seq 2 in the store
            b.reset(loop_id, actor="operator")
            b.reset(loop_id, actor="operator")
        assert {b.view(i).seq for i in loops} == {2}
        real_gone = a.cluster._gone

        def renewal_meanwhile(live):
            """Between the tick's reading of the lost shards and its acquisitions: the
            lease thread's renewal (the member row live again, the leases found taken),
            then b handing the shards a wins back (it sees a live)."""
            a.cluster._gone = real_gone
            a.cluster._renew(time.monotonic())
            assert not set(a.cluster.held) & shards
            wait_until(
                lambda: _held_by(pg_url, "b", shards) == 0, timeout=3 * LEASE_S, what="b's release"
            )
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
    finally:
        b.stop()
        a.stop()
