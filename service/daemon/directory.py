"""Read-only look-ups in a cluster's store for the admin API (any member answers for any
loop, :mod:`service.daemon.forward`): who owns a loop or a shard, and ``GET /cluster``.

Each opens a connection of its own (the API's threads never wait for the worker's or
the cluster thread's) and reads only small tables or one loop's row by its key: the
admin API must answer on a member that is loaded, and a query over every loop's row
(300,000 at a large site) took seconds on a loaded server. At most :data:`LOOKUPS` of
them are open at once (:func:`_connection`).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import psycopg

from service.daemon.store_pg import connect
from service.daemon.survey import SHARDS_SQL

if TYPE_CHECKING:
    from service.daemon.cluster import Cluster

LOOKUPS = 4
"""Look-ups of a member's admin API open at once; the others wait their turn. Reads need
no token, and every read of a loop another member holds is a look-up: unbounded, a flood
of them opened a connection each, up to the API's 40 threads per member, and PostgreSQL's
``max_connections`` (100 by default) is shared with every member's commits and leases,
which fail when it runs out (the tuner exits after ``store_failure_exit_s``)."""
_lookups = threading.BoundedSemaphore(LOOKUPS)


@contextmanager
def _connection(url: str) -> Iterator[psycopg.Connection]:
    """A connection to the store for one look-up, once fewer than LOOKUPS are open."""
    with _lookups, connect(url) as conn:
        yield conn


def view(cluster: Cluster) -> dict:
    """``GET /cluster``: the members with their URLs, whether live, their loop counts
    (as of their last renewal, within a tick: 0 once not live) and shards (their live
    leases), and the loops of shards no live member holds (a failover in progress)."""
    with _connection(cluster.url) as conn:
        rows = conn.execute(
            "SELECT m.instance_id, m.api_url, m.expires > clock_timestamp(), m.loops, "
            "(SELECT count(*) FROM leases l WHERE l.owner = m.instance_id "
            " AND l.expires > clock_timestamp()) "
            "FROM members m ORDER BY m.instance_id"
        ).fetchall()
        leased = {
            r[0] for r in conn.execute("SELECT shard FROM leases WHERE expires > clock_timestamp()")
        }
        free = [r[0] for r in conn.execute(SHARDS_SQL) if r[0] not in leased]
        unowned = 0
        if free:  # (none but during a failover or before the first tick)
            (unowned,) = conn.execute(
                "SELECT count(*) FROM loops WHERE shard = ANY(%s)", (free,)
            ).fetchone()
    return {
        "self": cluster.member,
        "lease_s": cluster.lease_s,
        "members": [
            {"instance_id": i, "api_url": u, "live": live, "loops": n if live else 0, "shards": s}
            for i, u, live, n, s in rows
        ],
        "unowned_loops": unowned,
        "adoptions": list(cluster.adoptions),
    }


def shard_owner_url(url: str, shard: str) -> str | None:
    """The API URL of the live member holding ``shard``'s lease (None: nobody)."""
    with _connection(url) as conn:
        row = conn.execute(
            "SELECT m.api_url FROM leases l JOIN members m ON m.instance_id = l.owner "
            "WHERE l.shard = %s AND l.expires > clock_timestamp()",
            (shard,),
        ).fetchone()
    return None if row is None else row[0]


def stored(url: str, loop_id: str) -> bool:
    """Whether the loop is in the store (registered through any member)."""
    with _connection(url) as conn:
        return conn.execute("SELECT 1 FROM loops WHERE id = %s", (loop_id,)).fetchone() is not None


def owner_url(url: str, loop_id: str) -> str | None:
    """The API URL of the member owning a stored loop (None: not stored, or no live
    owner right now)."""
    with _connection(url) as conn:
        row = conn.execute(
            "SELECT m.api_url FROM loops p JOIN leases l ON l.shard = p.shard "
            "JOIN members m ON m.instance_id = l.owner "
            "WHERE p.id = %s AND l.expires > clock_timestamp()",
            (loop_id,),
        ).fetchone()
    return None if row is None else row[0]
