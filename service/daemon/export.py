"""``pitune store export``: the audit (gains) history of a tuner's store as JSON lines.

Reads the database read-only, so it runs beside the tuner that owns it (SQLite WAL):
archive the history before the retention policy prunes it (or let the tuner archive
pruned rows itself: ``history_archive``). Rows the tuner committed but has not moved
out of its journal yet (the last seconds) are not in the audit table yet; they are
exported by the next run (``--since-id`` the last id exported)::

    pitune store export --db pitune.db > audit.jsonl
    pitune store export --db pitune.db --loop LIC-101 --since-id 123456 --out more.jsonl
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

from service.daemon.store import export_audit


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="store_command", required=True)
    export = sub.add_parser("export", help="write the audit history as JSON lines")
    export.add_argument("--db", type=Path, default=Path("pitune.db"), help="the store")
    export.add_argument("--loop", default=None, help="only this loop's rows")
    export.add_argument("--since-id", type=int, default=0, help="only rows after this id")
    export.add_argument("--out", type=Path, default=None, help="file (default: stdout)")


def run(args: argparse.Namespace) -> int:
    if not args.db.is_file():
        print(f"no store at {args.db}", file=sys.stderr)
        return 1
    db = sqlite3.connect(f"file:{args.db}?mode=ro", uri=True)
    try:
        if args.out is None:
            n = export_audit(db, sys.stdout.buffer, args.loop, args.since_id)
            sys.stdout.buffer.flush()
        else:
            with open(args.out, "wb") as out:
                n = export_audit(db, out, args.loop, args.since_id)
    finally:
        db.close()
    print(f"{n} audit rows exported", file=sys.stderr)
    return 0
