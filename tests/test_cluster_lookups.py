"""The admin API's look-ups in a cluster's store (:mod:`service.daemon.directory`) are
bounded: reads need no token, and each read of a loop another member holds is a look-up
on a connection of its own, against PostgreSQL's ``max_connections``, which the
members' commits and leases share."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from service.daemon import directory
from service.daemon.store_pg import PgStore

pytestmark = pytest.mark.timeout(60)
CALLERS = 24
"""Concurrent requests for loops held elsewhere (the API runs up to 40 at once)."""


def test_a_flood_of_reads_opens_at_most_lookups_connections(pg_url, monkeypatch):
    PgStore(pg_url).close()  # the schema
    opened, most, lock = [0], [0], threading.Lock()
    crowded = threading.Event()  # more connections open than the bound allows
    real = directory.connect

    def counted(url):
        conn = real(url)
        with lock:
            opened[0] += 1
            most[0] = max(most[0], opened[0])
            if opened[0] > directory.LOOKUPS:
                crowded.set()
        # held open a moment, as under a loaded server: without the bound, all callers
        # are inside at once and the event ends the wait; with it, the wait runs out
        crowded.wait(timeout=0.2)
        return _Closing(conn, opened, lock)

    monkeypatch.setattr(directory, "connect", counted)
    with ThreadPoolExecutor(CALLERS) as pool:
        answers = list(pool.map(lambda i: directory.owner_url(pg_url, f"L{i}"), range(CALLERS)))
    assert answers == [None] * CALLERS  # not stored: no owner
    assert most[0] <= directory.LOOKUPS and not crowded.is_set()


class _Closing:
    """The real connection, counted closed when its ``with`` block ends."""

    def __init__(self, conn, opened, lock) -> None:
        self.conn, self.opened, self.lock = conn, opened, lock

    def __enter__(self):
        return self.conn.__enter__()

    def __exit__(self, *exc):
        try:
            return self.conn.__exit__(*exc)
        finally:
            with self.lock:
                self.opened[0] -= 1
