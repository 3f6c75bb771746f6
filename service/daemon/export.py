"""``pitune store export``: the audit (gains) history of a tuner's store as JSON lines.

Reads the database read-only, so it runs beside the tuner that owns it (SQLite WAL):
archive the history before the retention policy prunes it (or let the tuner archive
pruned rows itself: ``history_archive``). Rows the tuner committed but has not moved
out of its journal yet (the last seconds) are not in the audit table yet; they are
exported by the next run (``--since-id`` the last id exported)::

    pitune store export --db pitune.db > audit.jsonl
    pitune store export --db pitune.db --loop LIC-101 --since-id 123456 --out more.jsonl

A PostgreSQL store (``--db postgresql://...``, the password in ``PGPASSWORD``) is read
in a read-only transaction; it has no journal, so every committed row is exported.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import sys
from pathlib import Path

from service.daemon.retention_store import export_audit
from service.daemon.settings import POSTGRES_SCHEMES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="store_command", required=True)
    export = sub.add_parser("export", help="write the audit history as JSON lines")
    export.add_argument(
        "--db", default="pitune.db", help="the store: an SQLite file or a PostgreSQL URL"
    )
    export.add_argument("--loop", default=None, help="only this loop's rows")
    export.add_argument("--since-id", type=int, default=0, help="only rows after this id")
    export.add_argument("--out", type=Path, default=None, help="file (default: stdout)")


def _open(location: str):
    """A read-only connection with sqlite3's ``execute`` (None: no such SQLite file)."""
    if location.startswith(POSTGRES_SCHEMES):
        from service.daemon.store_pg import Adapter, connect

        conn = connect(location)
        conn.execute("SET default_transaction_read_only = on")
        return Adapter(conn)
    if not Path(location).is_file():
        return None
    return sqlite3.connect(f"file:{location}?mode=ro", uri=True)


def run(args: argparse.Namespace) -> int:
    db = _open(args.db)
    if db is None:
        print(f"no store at {args.db}", file=sys.stderr)
        return 1
    try:
        if args.out is None:
            try:
                n = export_audit(db, sys.stdout.buffer, args.loop, args.since_id)
                sys.stdout.buffer.flush()
            except BrokenPipeError:  # the reader stopped early (| head): not an error
                # (Python's own flush at exit would raise again on the closed pipe)
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return 0
        else:
            with open(args.out, "wb") as out:
                n = export_audit(db, out, args.loop, args.since_id)
    finally:
        getattr(db, "conn", db).close()
    print(f"{n} audit rows exported", file=sys.stderr)
    return 0
