"""Retention in a cluster (real PostgreSQL, in-process members): each member prunes only
the audit history of the loops it owns, one member (the first of the live ones) that of
the deleted loops, and ages go by the database's clock, so a member whose wall clock
runs far ahead (a bad NTP or RTC step) prunes nothing that is young."""

from __future__ import annotations

import threading
import time

import psycopg
import pytest

from service.daemon.shards import assign
from service.daemon.tuner import Tuner
from service.engine.audit import audit_row
from service.engine.config import LoopConfig
from tests.test_cluster_membership import LEASE_S
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
DAY = 86400.0
ROWS = 10
"""History rows written per loop (30 days old by the database's clock)."""
KEEP_DELETED = 3


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path / name, db_path=url, instance_id=name, cluster_lease_s=LEASE_S,
        history_max_rows_deleted=KEEP_DELETED, **extra,
    )  # fmt: skip
    tuner = Tuner(settings)
    tuner._next_prune = tuner.clock.monotonic() + 1e6  # passes only when the test says
    return tuner.start()


def _rows(url: str) -> dict[str, int]:
    with psycopg.connect(url) as conn:
        return dict(conn.execute("SELECT loop_id, count(*) FROM audit GROUP BY loop_id"))


def _pass_with_clock_ahead(member: Tuner) -> None:
    """One retention pass of ``member``, its wall clock 400 days ahead."""
    done = threading.Event()
    prune = member.store.prune

    def pruned(*args, **kwargs):
        try:
            return prune(*args, **kwargs)
        finally:
            if not member._prune_todo:  # the pass's last call (PRUNE_BUDGET_S each)
                done.set()

    real = time.time
    member.store.prune, member.clock.wall = pruned, lambda: real() + 400 * DAY
    member._next_prune = 0.0
    member._wake()
    assert done.wait(30.0), "no retention pass"
    assert member.retention_failure is None


def test_each_member_prunes_its_own_loops_by_the_databases_clock(tmp_path, pg_url):
    a = _member(tmp_path, pg_url, "a")
    try:
        b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
        try:
            young, old = ["Y0", "Y1", "Y2"], ["O0", "O1", "O2"]
            ids = [*young, *old, "D"]
            # one gateway, one shard: the member that wins it owns every loop
            owner, other = (a, b) if assign(["gw:gwA"], ["a", "b"])["gw:gwA"] == "a" else (b, a)
            a.register_many([LoopConfig(**loop_body(i, gateway="gwA")) for i in ids])
            wait_until(lambda: a.cluster.members == b.cluster.members == ["a", "b"]
                       and len(owner.loop_ids()) == len(ids), timeout=30.0,
                       what="both members live, the shard's winner owning every loop")  # fmt: skip
            now = owner.store.wall_now()  # the policy keeps 365 days
            with psycopg.connect(pg_url) as conn:  # the old loops registered 401 days ago:
                conn.execute(  # the age prunes a prefix of a loop's rows (docs/tuner.md)
                    "UPDATE audit SET wall_time = wall_time - %s WHERE loop_id = ANY(%s)",
                    (401 * DAY, old),
                )
            ages = {**dict.fromkeys(young, 30 * DAY), **dict.fromkeys(old, 400 * DAY), "D": 0.0}
            owner.store.record_gains([], [
                audit_row(i, now - ages[i] + k, None, k, "auto", "agent", (0.5, 0.01), (0.5, 0.01))
                for i in ids for k in range(1, ROWS + 1)
            ])  # fmt: skip
            owner.delete("D")
            before = _rows(pg_url)
            assert before == {**dict.fromkeys(ids, ROWS + 1), "D": ROWS + 2}

            # the member owning no loop prunes none of the other's, old or young; the
            # deleted loop's tail is pruned by the first of the live members ("a") alone
            _pass_with_clock_ahead(other)
            after_other = {**before, "D": KEEP_DELETED} if other is a else before
            assert _rows(pg_url) == after_other
            # the owner prunes its loops' old rows but the newest, not the young ones
            _pass_with_clock_ahead(owner)
            assert _rows(pg_url) == {**after_other, **dict.fromkeys(old, 1), "D": KEEP_DELETED}
            assert owner.pruned == len(old) * ROWS + (ROWS + 2 - KEEP_DELETED) * (owner is a)
            assert other.pruned == (ROWS + 2 - KEEP_DELETED) * (other is a)
        finally:
            b.stop()
    finally:
        a.stop()
