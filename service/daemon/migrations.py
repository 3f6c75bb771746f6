"""Versioned schema migrations of the store, SQLite and PostgreSQL.

Each migration is a numbered step with one SQL script per dialect; ``schema_version``
records the steps applied (one row each, with the wall time). Opening a store applies
the missing steps in order, each in its own transaction with its version row, so a
crash in the middle leaves the store at the last whole step. A store whose version is
above :data:`LATEST` was written by a newer pitune: opening it fails instead of
writing rows an older schema does not describe.

Version 1 is the schema every store had before versions were recorded (its
``CREATE ... IF NOT EXISTS`` statements leave such a store as it is, then record it).
Version 2 adds what several tuners sharing one PostgreSQL store need: each loop's
ownership ``shard`` (its gateway, or a hash bucket of its id; see
:mod:`service.daemon.shards`), the ``members`` of the cluster and the ``leases`` of the
shards with their fencing tokens. An SQLite store gets the same tables, unused by its
single tuner, so both backends share one schema and one set of queries.
"""

from __future__ import annotations

import time
from collections.abc import Callable

SQLITE_V1 = """
CREATE TABLE IF NOT EXISTS loops (
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    kp REAL NOT NULL,
    ki REAL NOT NULL,
    seq INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS snapshots (
    id TEXT PRIMARY KEY REFERENCES loops(id) ON DELETE CASCADE,
    hidden BLOB NOT NULL,
    runtime TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    loop_id TEXT NOT NULL,
    wall_time REAL NOT NULL,
    t REAL,
    seq INTEGER NOT NULL,
    mode TEXT NOT NULL,
    reason TEXT NOT NULL,
    kp_old REAL, ki_old REAL, kp_new REAL, ki_new REAL,
    detail TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS audit_loop ON audit (loop_id, id);
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS journal (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    rows BLOB NOT NULL,  -- JSON {"gains": [[kp, ki, seq, id], ...], "audit": [[...], ...]}
    done INTEGER NOT NULL DEFAULT 0  -- rows applied so far: the gains first, then the audit
);
"""
"""The schema of every SQLite store written before versions were recorded."""

_CLUSTER_TABLES = """
CREATE TABLE members (
    instance_id TEXT PRIMARY KEY,
    api_url TEXT NOT NULL,
    started REAL NOT NULL,
    expires {time} NOT NULL  -- the member is live until then (the database's clock)
);
CREATE TABLE leases (
    shard TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    token BIGINT NOT NULL,  -- the fencing token: larger at every change of owner
    expires {time} NOT NULL
);
"""

SQLITE_V2 = (
    "ALTER TABLE loops ADD COLUMN shard TEXT;\n"
    "CREATE INDEX loops_shard ON loops (shard);\n" + _CLUSTER_TABLES.format(time="REAL")
)

PG_V1 = """
CREATE TABLE IF NOT EXISTS loops (
    ord BIGINT GENERATED ALWAYS AS IDENTITY,  -- registration order (SQLite's rowid)
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    kp DOUBLE PRECISION NOT NULL,
    ki DOUBLE PRECISION NOT NULL,
    seq BIGINT NOT NULL
);
CREATE TABLE IF NOT EXISTS snapshots (
    id TEXT PRIMARY KEY REFERENCES loops(id) ON DELETE CASCADE,
    hidden BYTEA NOT NULL,
    runtime TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS audit (
    id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    loop_id TEXT NOT NULL,
    wall_time DOUBLE PRECISION NOT NULL,
    t DOUBLE PRECISION,
    seq BIGINT NOT NULL,
    mode TEXT NOT NULL,
    reason TEXT NOT NULL,
    kp_old DOUBLE PRECISION, ki_old DOUBLE PRECISION,
    kp_new DOUBLE PRECISION, ki_new DOUBLE PRECISION,
    detail TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS audit_loop ON audit (loop_id, id);
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
"""
"""PostgreSQL version 1: SQLite's tables without the journal (a PostgreSQL commit of a
step batch's rows is fast enough to be the commit before publishing)."""

PG_V2 = (
    "ALTER TABLE loops ADD COLUMN shard TEXT;\n"
    "CREATE INDEX loops_shard ON loops (shard);\n" + _CLUSTER_TABLES.format(time="TIMESTAMPTZ")
)

V3 = "ALTER TABLE members ADD COLUMN loops INTEGER NOT NULL DEFAULT 0"
"""Version 3: each member writes the number of loops in its engine with every renewal,
so ``GET /cluster`` reads the members' rows instead of counting every loop's row (a
scan of the whole ``loops`` table, which took seconds on a loaded server at 300,000
loops)."""

V4 = "ALTER TABLE loops ADD COLUMN epoch BIGINT"
"""Version 4: the epoch each loop's gains were last committed (and their message
published) under, which its state replies carry. With the current start's epoch instead,
a reply after a restart or a failover ordered above the gateway's last message of the
same seq, and the gateway wrote the stored gains over an operator's change made while
the tuner was down (an integrator's review, session 36). NULL: none recorded (a row of
an older version, or a loop registered again): the current epoch, as before."""

MIGRATIONS: dict[str, list[str]] = {
    "sqlite": [SQLITE_V1, SQLITE_V2, V3, V4],
    "postgresql": [PG_V1, PG_V2, V3, V4],
}
LATEST = 4
VERSION_TABLE = (
    "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied REAL NOT NULL)"
)


class SchemaTooNew(RuntimeError):
    """The store was written by a newer pitune (its schema version is above LATEST)."""


def current_version(execute: Callable) -> int:
    """The store's schema version (0: nothing recorded)."""
    row = execute("SELECT MAX(version) FROM schema_version").fetchone()
    return int(row[0] or 0)


def migrate(dialect: str, execute: Callable, transaction: Callable) -> int:
    """Bring the store to :data:`LATEST`; returns the version it had before.

    ``execute(sql, params)`` runs one statement and ``transaction()`` is a context
    manager around one transaction (the dialect's). Scripts run statement by statement
    (none has a ``;`` inside), since SQLite's ``executescript`` commits first.
    """
    with transaction():
        execute(VERSION_TABLE, ())
    before = current_version(lambda sql: execute(sql, ()))
    if before > LATEST:
        raise SchemaTooNew(
            f"the store's schema is version {before}, this pitune knows up to {LATEST}: "
            "it was written by a newer pitune; run that version (or a newer one)"
        )
    placeholder = "?" if dialect == "sqlite" else "%s"
    for version, sql in enumerate(MIGRATIONS[dialect][before:], start=before + 1):
        with transaction():
            for statement in sql.split(";"):
                if statement.strip():
                    execute(statement, ())
            execute(
                f"INSERT INTO schema_version (version, applied) VALUES ({placeholder}, "
                f"{placeholder})",
                (version, time.time()),
            )
    return before
