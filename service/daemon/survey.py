"""What a cluster member's tick reads of the cluster (:mod:`service.daemon.cluster`): the
live members, the shards with loops and when each other member's leases run out; and the
members dead long ago it forgets (:data:`FORGET_S`)."""

from __future__ import annotations

import psycopg

SHARDS_SQL = (
    "WITH RECURSIVE s AS ("
    "(SELECT shard FROM loops ORDER BY shard LIMIT 1) UNION ALL "
    "SELECT (SELECT shard FROM loops WHERE shard > s.shard ORDER BY shard LIMIT 1) "
    "FROM s WHERE s.shard IS NOT NULL) "
    "SELECT shard FROM s WHERE shard IS NOT NULL"
)
"""The shards with loops, one index probe per shard on ``loops_shard`` (a loose index
scan): ``SELECT DISTINCT shard`` reads every loop's row, every tick, on every member
(parallel workers at 300,000 loops)."""
LAST_EXPIRY_SQL = (
    "SELECT owner, extract(epoch FROM max(expires) - clock_timestamp())::float8 FROM ("
    "SELECT instance_id AS owner, expires FROM members WHERE instance_id <> %s "
    "AND expires > clock_timestamp() UNION ALL "
    "SELECT owner, expires FROM leases WHERE owner <> %s AND expires > clock_timestamp()"
    ") AS e GROUP BY owner"
)
"""Each other member's seconds until it has nothing unexpired left (its row and every
lease it holds): a dead member's leases were renewed one by one, each after the
member's commits in flight on it (``FOR SHARE``), so they expire up to a busy worker's
commit apart; a tick timed to the first of them took one shard and left the rest to a
tick after that shard's loading (at 30,000 loops: 8 s later)."""


FORGET_S = 3600.0
"""Seconds after its row and its last lease expired (the database's clock) that a member
that never left cleanly (killed: OOM, power cut) is deleted from ``members``, so that
``GET /cluster`` stops listing it: with the default instance id (host-pid) every such
restart left one more dead row, and nothing else removes them. Long past any failover
(which takes a dead member's leases within a lease) or pause a member survives: one
that comes back later finds its row gone and joins again (``Cluster._renew_held``)."""
FORGET_SQL = (
    "DELETE FROM members m WHERE m.instance_id <> %s "
    "AND m.expires < clock_timestamp() - make_interval(secs => %s) "
    "AND NOT EXISTS (SELECT 1 FROM leases l WHERE l.owner = m.instance_id "
    "AND l.expires > clock_timestamp() - make_interval(secs => %s))"
)
"""A no-op most ticks (no row deleted writes nothing): the members table holds a row
per member, ``leases`` one per shard."""


def survey(
    conn: psycopg.Connection, member: str
) -> tuple[dict[str, float], list[str], dict[str, float]]:
    """(live members with the seconds left on their rows, shards with loops, each member
    other than ``member``'s seconds until its row and leases have all expired). A live
    member renews every tick, so its expiry is about ``lease_s`` away; a dead one's comes
    closer, and the tick that takes its leases is timed to it (``Cluster._next_due``)
    rather than up to a tick later. Deletes the members dead longer than
    :data:`FORGET_S` first."""
    conn.execute(FORGET_SQL, (member, FORGET_S, FORGET_S))
    live = dict(
        conn.execute(
            "SELECT instance_id, extract(epoch FROM expires - clock_timestamp())::float8 "
            "FROM members WHERE expires > clock_timestamp() ORDER BY instance_id"
        ).fetchall()
    )
    stored = [r[0] for r in conn.execute(SHARDS_SQL)]
    lasts = dict(conn.execute(LAST_EXPIRY_SQL, (member, member)).fetchall())
    return live, stored, lasts
