"""A cluster member's periodic snapshot is written off its worker thread
(service/daemon/snapwriter.py), in process with a real PostgreSQL store: the worker
does not wait for the write, and a snapshot written later by the worker itself (or a
delete) is never overtaken by an older queued chunk."""

from __future__ import annotations

import threading

import psycopg
import pytest

from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(60)


class _Held:
    """The writer's store write, held until :attr:`release` is set."""

    def __init__(self, write) -> None:
        self.write = write
        self.release = threading.Event()
        self.started = threading.Event()

    def __call__(self, rows, fence) -> None:
        self.started.set()
        assert self.release.wait(30.0)
        self.write(rows, fence)


def _runtime(url: str) -> dict[str, str]:
    with psycopg.connect(url) as conn:
        return dict(conn.execute("SELECT id, runtime FROM snapshots"))


@pytest.fixture
def member(tmp_path, pg_url):
    tuner = Tuner(tuner_settings(tmp_path, db_path=pg_url, instance_id="a")).start()
    try:
        tuner.register_many([LoopConfig(**loop_body(f"L{i}")) for i in range(6)])
        yield tuner
    finally:
        tuner.snapshot_writer._write = tuner.store.snapshot
        tuner.stop()


def _in_thread(call) -> threading.Thread:
    thread = threading.Thread(target=call, daemon=True)
    thread.start()
    return thread


def test_the_worker_does_not_wait_for_the_periodic_snapshots_write(member, pg_url):
    held = _Held(member.store.snapshot)
    member.snapshot_writer._write = held
    before = _runtime(pg_url)
    member._snapshot_todo = ["L0", "L1"]
    chunk = _in_thread(member._snapshot_some)
    chunk.join(10.0)
    assert not chunk.is_alive()  # handed over while the write is still held
    assert held.started.wait(10.0)
    assert _runtime(pg_url) == before
    held.release.set()
    assert member.snapshot_writer.drain(10.0)
    after = _runtime(pg_url)
    assert {"L0", "L1"} <= set(after)


def test_a_queued_chunk_never_overwrites_a_newer_snapshot_or_outlives_a_delete(member, pg_url):
    held = _Held(member.store.snapshot)
    member.snapshot_writer._write = held
    writer = member.snapshot_writer
    old = [(loop_id, hidden, '{"stale": true}') for loop_id, hidden, _ in
           member.table.snapshot(["L2", "L3", "L4", "L5"])]  # fmt: skip
    fence = member._fence(["L2", "L3", "L4", "L5"])
    writer.submit(old[:1], fence)  # being written (held)
    assert held.started.wait(10.0)
    writer.submit(old[1:], fence)  # queued: L3, L4, L5
    # the worker's own snapshot of L3 (a commit's, a release's) and a delete of L4
    # wait for the chunk in flight, and drop theirs from the queued one
    own = _in_thread(lambda: member._write_snapshot(["L3"]))
    gone = _in_thread(lambda: member.delete("L4"))
    own.join(0.5)
    assert own.is_alive()  # behind the chunk being written
    held.release.set()
    own.join(10.0)
    gone.join(10.0)
    assert writer.drain(10.0)
    wait_until(lambda: writer.idle(), 10.0)
    rows = _runtime(pg_url)
    assert rows["L2"] == '{"stale": true}'  # the chunk in flight landed
    assert rows["L3"] != '{"stale": true}'  # its newer row stayed
    assert rows["L5"] == '{"stale": true}'  # the queued chunk's other rows landed
    assert "L4" not in rows  # deleted, not brought back by the queued chunk
    # (nor by the registration's NOTIFY if its store read came before the delete:
    # tests/test_cluster_reload.py)
    assert "L4" not in member.loop_ids()


def test_a_chunk_after_the_database_dropped_the_connection_is_written_at_once(member, pg_url):
    """A server restart (here: the snapshots' backend terminated, as a restart does) is
    found only by the statement sent on the dead connection: the chunk goes again on a
    new one, not a snapshot interval or more later."""
    member.store.snapshot(member.table.snapshot(["L0"]))  # the snapshots' connection open
    pid = member.store._snap_conn.info.backend_pid
    with psycopg.connect(pg_url, autocommit=True) as conn:
        conn.execute("DELETE FROM snapshots WHERE id IN ('L1', 'L2')")
        assert conn.execute("SELECT pg_terminate_backend(%s)", (pid,)).fetchone() == (True,)
        gone = "SELECT count(*) = 0 FROM pg_stat_activity WHERE pid = %s"
        wait_until(lambda: conn.execute(gone, (pid,)).fetchone()[0], 10.0, what="its end")
    member._snapshot_todo = ["L1", "L2"]
    member._snapshot_some()  # on the worker's thread in the tuner: here, the test's
    assert member.snapshot_writer.drain(10.0)
    assert {"L1", "L2"} <= set(_runtime(pg_url))
    assert member.store._snap_conn.info.backend_pid != pid
