"""The store's two backends: versioned migrations (an SQLite store of the schema before
versions were recorded upgrades in place), and the PostgreSQL store keeping the SQLite
store's guarantees, against a real PostgreSQL server."""

import io
import socket
import sqlite3

import orjson
import psycopg
import pytest

from service.daemon import migrations
from service.daemon.shards import shard_of
from service.daemon.store import Store
from service.daemon.store_pg import Fenced, PgStore
from service.engine.audit import audit_row
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body

pytestmark = pytest.mark.timeout(60)


def _config(loop_id: str, **overrides) -> LoopConfig:
    return LoopConfig(**loop_body(loop_id, **overrides))


def _registered(config: LoopConfig, seq: int = 0):
    return audit_row(config.id, 1.0, None, seq, "auto", "registered", None, (0.5, 0.01), "{}")


def test_an_sqlite_store_of_the_unversioned_schema_upgrades_in_place(tmp_path):
    path = tmp_path / "old.db"
    config = _config("OLD-1", gateway="gw1")
    with sqlite3.connect(path) as db:  # the schema and rows of a pitune before versions
        db.executescript(migrations.SQLITE_V1)
        db.execute(
            "INSERT INTO loops (id, config, kp, ki, seq) VALUES (?, ?, 0.7, 0.02, 41)",
            (config.id, config.model_dump_json()),
        )
        db.execute(
            "INSERT INTO audit (loop_id, wall_time, seq, mode, reason) "
            "VALUES ('OLD-1', 1.0, 41, 'auto', 'agent')"
        )
        db.execute(
            "INSERT INTO journal (rows) VALUES (?)",
            (orjson.dumps({"gains": [[0.8, 0.03, 42, "OLD-1"]], "audit": []}),),
        )
    store = Store(path)
    try:
        assert store.migrated_from == 0
        (loop,) = store.load()  # the pending journal row applied
        assert (loop.kp, loop.ki, loop.seq) == (0.8, 0.03, 42)
        assert store.last_seqs(["OLD-1"]) == {"OLD-1": 41}
    finally:
        store.close()
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT MAX(version) FROM schema_version").fetchone() == (
            migrations.LATEST,
        )
        assert db.execute("SELECT shard FROM loops").fetchone() == ("gw:gw1",)
    again = Store(path)  # opening an up-to-date store changes nothing
    assert again.migrated_from == migrations.LATEST
    again.close()


def test_a_store_of_a_newer_schema_is_refused(tmp_path):
    path = tmp_path / "new.db"
    Store(path).close()
    with sqlite3.connect(path) as db:
        db.execute("INSERT INTO schema_version VALUES (99, 0.0)")
    with pytest.raises(migrations.SchemaTooNew, match="version 99"):
        Store(path)


def test_postgres_store_round_trip(pg_url):
    store = PgStore(pg_url)
    try:
        assert store.migrated_from == 0
        configs = [_config(f"L{i}") for i in range(3)] + [_config("G1", gateway="gw1")]
        store.insert_loops(configs, [_registered(c) for c in configs], [0, 0, 5, 0])
        with pytest.raises(store.integrity_errors):
            store.insert_loops(configs[:1], [_registered(configs[0])], [0])
        # what a registration's 409 names, read right after the failed insert
        assert store.gateways_of(["nope", "G1", "L0"]) == {"G1": "gw1", "L0": None}
        store.record_gains(
            [(0.6, 0.02, 1, "L0"), (0.7, 0.03, 6, "L2")],
            [audit_row("L0", 2.0, 1.0, 1, "auto", "agent", (0.5, 0.01), (0.6, 0.02))],
        )
        # one statement with binary arrays: ints among floats and NULLs are typed per column
        reset = audit_row("L2", 2, None, 6, "auto", "reset", (1, 0.03), (0.7, 0.03), "by op")
        store.record_gains([(1, 0.03, 6, "L2")], [reset])
        store.record_gains([], [])  # nothing to write: no statement
        store.snapshot([("L0", b"\x00\x01", '{"last_t": 1.0}')])
        loaded = {s.config.id: s for s in store.load()}
        assert [s.config.id for s in store.load()] == ["L0", "L1", "L2", "G1"]  # order kept
        assert (loaded["L0"].kp, loaded["L0"].seq, loaded["L0"].hidden) == (0.6, 1, b"\x00\x01")
        assert (loaded["L2"].kp, loaded["L2"].seq, loaded["L1"].hidden) == (1.0, 6, None)
        (reset,) = store.history("L2", 0, 10)[1][:1]
        assert (reset.t, reset.kp_old, reset.detail) == (None, 1.0, "by op")
        assert [s.config.id for s in store.load(["gw:gw1"])] == ["G1"]
        assert store.last_seqs(["L0", "L2", "nope"]) == {"L0": 1, "L2": 6}
        total, items = store.history("L0", 0, 10)
        assert total == 2 and items[0].reason == "agent" and items[0].kp_new == 0.6
        buf = io.BytesIO()
        assert store.export(buf) == 6
        assert orjson.loads(buf.getvalue().splitlines()[-1])["loop_id"] == "L2"
        store.delete_loop("L1", audit_row("L1", 3.0, None, 0, "auto", "deleted", (0.5, 0.01), None))
        assert "L1" not in {s.config.id for s in store.load()}
        epochs = [store.next_epoch(1.0), store.next_epoch(1.0)]
        assert epochs[1] > epochs[0]  # on the database's clock, not the 1.0 passed
        assert store.prune(["L0"], older_than=None, keep_rows=1, keep_rows_deleted=1) == 1
    finally:
        store.close()
    again = PgStore(pg_url)
    assert again.migrated_from == migrations.LATEST
    assert shard_of("G1", "gw1") == "gw:gw1"
    again.close()


def test_a_postgres_commit_without_its_lease_is_fenced_and_writes_nothing(pg_url):
    store = PgStore(pg_url)
    try:
        config = _config("F1")
        store.insert_loops([config], [_registered(config)], [0])
        shard = shard_of("F1", None)
        with store.transaction() as db:
            db.execute(
                "INSERT INTO leases (shard, owner, token, expires) "
                "VALUES (?, 'a', 7, clock_timestamp() + interval '5 seconds')",
                (shard,),
            )
        row = [audit_row("F1", 2.0, 1.0, 1, "auto", "agent", (0.5, 0.01), (0.6, 0.02))]
        store.record_gains([(0.6, 0.02, 1, "F1")], row, fence=("a", {shard: 7}))
        store.snapshot([("F1", b"\x00" * 4, '{"n": 1}')], fence=("a", {shard: 7}))
        for fence in (("a", {shard: 6}), ("b", {shard: 7})):  # an old token, another member
            with pytest.raises(Fenced):
                store.record_gains([(0.9, 0.09, 2, "F1")], row, fence=fence)
            with pytest.raises(Fenced):
                store.snapshot([("F1", b"\x01" * 4, '{"n": 2}')], fence=fence)
        with store.transaction() as db:  # the lease runs out
            db.execute("UPDATE leases SET expires = clock_timestamp() - interval '1 second'")
        with pytest.raises(Fenced):
            store.record_gains([(0.9, 0.09, 2, "F1")], row, fence=("a", {shard: 7}))
        (loop,) = store.load()
        assert (loop.kp, loop.seq) == (0.6, 1)
        assert (loop.hidden, loop.runtime) == (b"\x00" * 4, '{"n": 1}')  # the fenced-in one
        assert store.history("F1", 0, 10)[0] == 2  # registered + the one fenced-in step
    finally:
        store.close()


def test_a_lost_postgres_connection_is_reopened(pg_url):
    store = PgStore(pg_url)
    try:
        with psycopg.connect(pg_url, autocommit=True) as admin:
            admin.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE datname = current_database() AND pid <> pg_backend_pid()"
            )
        with pytest.raises(psycopg.OperationalError):
            store.load()
        assert store.load() == []
    finally:
        store.close()


@pytest.mark.timeout(240)  # two tuners' start-ups (torch imported first), each up to 90 s
def test_an_unreachable_postgres_store_is_one_line_without_the_password(tmp_path, pg_server):
    from service.daemon import main as daemon
    from tests.test_operability_startup import one_line, start

    with socket.socket() as held:  # bound, never listening: refused, and no one else's
        held.bind(("127.0.0.1", 0))
        dead = f"postgresql://pitune:s3cret@127.0.0.1:{held.getsockname()[1]}/pitune"
        line = one_line(start(tmp_path, "--db", dead), daemon.EXIT_CANT_CREATE,
                        "cannot open the store")  # fmt: skip
    assert "s3cret" not in line and "***" in line
    newer = pg_server.create_database()
    PgStore(newer).close()
    with psycopg.connect(newer, autocommit=True) as conn:
        conn.execute("INSERT INTO schema_version VALUES (99, 0.0)")
    line = one_line(start(tmp_path, "--db", newer), daemon.EXIT_CANT_CREATE, "version 99")


def test_store_export_reads_a_postgres_store(pg_url, tmp_path):
    import argparse

    from service.daemon import export

    store = PgStore(pg_url)
    configs = [_config("E1"), _config("E2")]
    store.insert_loops(configs, [_registered(c) for c in configs], [0, 0])
    store.close()
    out = tmp_path / "audit.jsonl"
    args = argparse.Namespace(db=pg_url, loop="E2", since_id=0, out=out)
    assert export.run(args) == 0
    (row,) = [orjson.loads(line) for line in out.read_bytes().splitlines()]
    assert (row["loop_id"], row["reason"]) == ("E2", "registered")
