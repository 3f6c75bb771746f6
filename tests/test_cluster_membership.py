"""Membership changes of a cluster, in-process (real PostgreSQL, real Zenoh sessions): a
member joining takes its share of the shards within a tick (the holder releases them,
no lease has to run out), one leaving cleanly hands its loops over within a tick, a
loop is never in two members' engines, and members killed long ago are forgotten."""

from __future__ import annotations

import time

import pytest

from service.daemon.directory import view
from service.daemon.store_pg import connect
from service.daemon.survey import FORGET_S
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 3.0


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path, db_path=url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


def _split(*tuners: Tuner) -> list[int]:
    loops = [set(t.loop_ids()) for t in tuners]
    assert len(loops) == 1 or not set.intersection(*loops)  # never in two engines
    return [len(s) for s in loops]


def test_members_joining_and_leaving_move_shards_within_a_tick(tmp_path, pg_url):
    configs = [LoopConfig(**loop_body(f"L{i:02d}")) for i in range(40)]
    configs += [LoopConfig(**loop_body(f"G{i}", gateway="gw1")) for i in range(10)]
    a = _member(tmp_path, pg_url, "a")
    try:
        a.register_many(configs)
        assert _split(a) == [50]
        joined = time.monotonic()
        b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
        try:
            wait_until(lambda: min(_split(a, b)) > 0 and sum(_split(a, b)) == 50, timeout=LEASE_S)
            assert time.monotonic() - joined < LEASE_S  # released, not expired
            gw = {"G0" in a.loop_ids(), "G0" in b.loop_ids()}
            assert gw == {True, False}
            owner = a if "G0" in a.loop_ids() else b
            assert {f"G{i}" for i in range(10)} <= set(owner.loop_ids())  # a gateway stays whole
            # each member's count as of its last renewal (a tick at most behind)
            wait_until(
                lambda: (
                    sorted((m["instance_id"], m["loops"]) for m in view(a.cluster)["members"])
                    == [("a", len(a.loop_ids())), ("b", len(b.loop_ids()))]
                ),
                timeout=LEASE_S,
            )
        finally:
            left = time.monotonic()
            b.stop()
        wait_until(lambda: _split(a) == [50], timeout=LEASE_S)
        assert time.monotonic() - left < LEASE_S  # handed over at once
        assert view(a.cluster)["unowned_loops"] == 0
        a.delete("G0")
        wait_until(lambda: view(a.cluster)["members"][0]["loops"] == 49, timeout=LEASE_S)
    finally:
        a.stop()


def test_members_dead_long_ago_are_forgotten_by_a_members_tick(tmp_path, pg_url):
    """Killed incarnations (host-pid ids, no clean leave) left their rows; a live member's
    tick deletes those whose row and every lease expired over FORGET_S ago, and keeps
    the recently dead (a failover may still be under way) and their leases' owners."""
    a = _member(tmp_path, pg_url, "a")
    try:
        dead = {  # instance id: (row expired, lease expired) seconds ago
            "host-101": (2 * FORGET_S, None),
            "host-102": (600.0, None),
            "host-103": (2 * FORGET_S, 1800.0),
            "host-104": (2 * FORGET_S, 2 * FORGET_S),
        }
        with connect(pg_url) as conn:
            for shard, (member, (row_s, lease_s)) in enumerate(dead.items()):
                conn.execute(
                    "INSERT INTO members (instance_id, api_url, started, expires) VALUES "
                    "(%s, 'http://x', 0, clock_timestamp() - make_interval(secs => %s))",
                    (member, row_s),
                )
                if lease_s is not None:
                    conn.execute(
                        "INSERT INTO leases (shard, owner, token, expires) VALUES "
                        "(%s, %s, 1, clock_timestamp() - make_interval(secs => %s))",
                        (f"gone-{shard}", member, lease_s),
                    )
        wait_until(
            lambda: (
                [m["instance_id"] for m in view(a.cluster)["members"]]
                == ["a", "host-102", "host-103"]
            ),
            timeout=3 * LEASE_S,
        )
        assert [m["live"] for m in view(a.cluster)["members"]] == [True, False, False]
    finally:
        a.stop()


def test_an_sqlite_tuner_has_no_cluster(tmp_path):
    from fastapi.testclient import TestClient

    from service.daemon.api import create_app

    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        assert client.get("/cluster").json() == {
            "self": "test-tuner",
            "members": [],
            "store": "sqlite",
        }
