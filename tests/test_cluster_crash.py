"""A member that crashed (its connections closed, so its Zenoh liveliness token gone)
loses its leases before they run out, and only then (real PostgreSQL, real Zenoh
sessions, in-process members): a member whose token is gone but which still renews
its leases (cut off from the bus only) keeps them, whatever the others believe (they
parse its loops ahead, then let them go), and one that stops renewing but keeps its
token (slow, paused) keeps them until they expire."""

from __future__ import annotations

import time

import pytest

from service.daemon.cluster import DEAD_AFTER_TICKS, TICKS_PER_LEASE
from service.daemon.directory import view
from service.daemon.store_pg import connect
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 5.0
TICK_S = LEASE_S / TICKS_PER_LEASE


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path, db_path=url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


def _pair(tmp_path, url: str) -> tuple[Tuner, Tuner]:
    """Two members sharing 40 loops on 4 gateways, each owning some."""
    a = _member(tmp_path, url, "a")
    b = _member(tmp_path, url, "b", zenoh_connect=a.settings.zenoh_listen)
    configs = [
        LoopConfig(**loop_body(f"G{g}-{i}", gateway=f"gw{g}")) for g in range(4) for i in range(10)
    ]
    a.register_many(configs)
    wait_until(
        lambda: (
            len(a.loop_ids()) + len(b.loop_ids()) == 40
            and min(len(a.loop_ids()), len(b.loop_ids())) > 0
        ),
        timeout=3 * LEASE_S,
        what="both members owning loops",
    )
    wait_until(lambda: "a" in b.bus.live_tuners(), timeout=LEASE_S, what="a's token seen by b")
    return a, b


def _stale(url: str, owner: str, ticks: float) -> bool:
    """Every lease of ``owner`` was last renewed more than ``ticks`` ago (database clock)."""
    with connect(url) as conn:
        (n,) = conn.execute(
            "SELECT count(*) FROM leases WHERE owner = %s AND "
            "expires >= clock_timestamp() + make_interval(secs => %s)",
            (owner, LEASE_S - ticks * TICK_S),
        ).fetchone()
    return n == 0


def _db(url: str, sql: str) -> float:
    with connect(url) as conn:
        return conn.execute(sql).fetchone()[0]


def _take(member: Tuner, shards: set[str], dead: set[str]) -> list[str]:
    with connect(member.cluster.url) as conn:
        return member.cluster._take(shards, member.store.next_epoch(time.time()), conn, dead)


def test_a_crashed_member_s_loops_are_taken_before_its_leases_run_out(tmp_path, pg_url):
    a, b = _pair(tmp_path, pg_url)
    try:
        theirs = set(a.cluster.held)
        # stopped, but its token still on the bus (a pause, a starved process): its
        # leases are late, not taken before they expire even by a member told it is dead
        a.cluster.halt()
        expiry = _db(
            pg_url, "SELECT extract(epoch FROM expires) FROM members WHERE instance_id = 'a'"
        )
        wait_until(lambda: _stale(pg_url, "a", DEAD_AFTER_TICKS), timeout=LEASE_S)
        assert b.cluster._gone({"a": 0.1, "b": LEASE_S}) == set()  # its token is there
        assert _take(b, theirs, set()) == []  # unexpired
        # its connections close (the process died): taken before the leases run out
        a.bus.close()
        wait_until(lambda: len(b.loop_ids()) == 40, timeout=LEASE_S, what="a's loops on b")
        assert _db(pg_url, "SELECT extract(epoch FROM clock_timestamp())") < expiry
        assert set(b.cluster.held) >= theirs
        members = {m["instance_id"]: m for m in view(b.cluster)["members"]}
        assert not members["a"]["live"] and members["b"]["loops"] == 40
    finally:
        b.stop()
        a.stop()


def test_a_member_cut_off_from_the_bus_keeps_its_leases(tmp_path, pg_url):
    a, b = _pair(tmp_path, pg_url)
    try:
        theirs = set(a.cluster.held)
        mine = set(b.loop_ids())
        a.bus.close()  # its token gone, its renewals go on
        # b saw the token go: it parses a's shards ahead of a takeover, at once
        wait_until(lambda: b.cluster._ahead == theirs, timeout=LEASE_S, what="parsing ahead")
        # whatever b believes, the database refuses: a renewed within the last ticks
        assert _take(b, theirs, {"a"}) == []
        assert set(a.cluster.held) == theirs and set(b.loop_ids()) == mine
        # a lease later a still renews: no longer suspect, the parsed loops let go
        wait_until(lambda: not b.cluster._ahead, timeout=3 * LEASE_S, what="parsing let go")
        assert set(a.cluster.held) == theirs and set(b.loop_ids()) == mine
    finally:
        b.stop()
        a.stop()
