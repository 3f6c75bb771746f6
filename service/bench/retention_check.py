"""What a retention run (:mod:`service.bench.retention`) measures and checks: the store's
size, the rows per loop, the disk budget the policy implies, and that no audit row the
policy protects was pruned.

The budget of a policy (documented in docs/tuner.md, Retention and disk use)::

    rows   = registered loops x history_max_rows_per_loop
           + deleted loops    x history_max_rows_deleted
    budget = rows x BYTES_PER_ROW + loops x BYTES_PER_LOOP + WAL_ALLOWANCE

A loop stepped more often than once per ``horizon / history_max_rows_per_loop`` (53 min
with the defaults) reaches the row cap within the horizon, so the cap is what bounds a
site: under the default policy a loop takes at most 10,000 x 300 bytes = 3 MB, 1,000
loops 3 GB.
"""

from __future__ import annotations

import sqlite3
import time
from contextlib import closing
from pathlib import Path

import numpy as np
import orjson

BYTES_PER_ROW = 400
"""Disk per audit row the budget allows, its index entry and page slack included (an
agent step's row holds ~170 bytes of data). Checked against ``size.audit_bytes_per_row``,
the bytes the rows and their index entries use in their pages (dbstat's ``pgsize -
unused``): 190-215 until session 17, 368 in ``tests/test_retention_run.py`` (pages then)
since hinted loops' steps are model-checked and a held step's row carries the check's
three predictions. Whole pages per kept row (``audit_page_bytes_per_row``) were that
check until session 40: since each pass cuts every loop to its run of young rows, a short
run keeps few rows in the pages that held more, whose slack once read 400+ (CI); the
peak file size is held to the budget whatever the slack (``peak_under_budget``)."""
BYTES_PER_LOOP = 6144
"""Disk per registered loop beside its audit rows: the loops row (config JSON, ~0.8 KB)
and the runtime snapshot (hidden state, counters, operating point and identification
events: 4.0-4.1 KB measured for a loop with 6 events, session 40)."""
WAL_ALLOWANCE = 128 << 20
"""The write-ahead log, which keeps the size of its largest transaction: a registration
or deletion applies the whole journal first (up to JOURNAL_BACKLOG = 100,000 rows under
load, ~80 MB measured in the 24-hour run)."""
YEAR_S = 365.0 * 86400.0
RL_PERIODS_S = (5.5, 27.5, 165.0, 825.0, 3300.0)
"""RL periods (5.5 tau) of the size-per-loop-year table: tau 1 s, 5 s, 30 s, 150 s, 10 min."""


def _ro(db: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30.0)


def db_bytes(db: Path) -> dict:
    """The store's file and write-ahead log sizes, bytes."""
    wal = Path(f"{db}-wal")
    file_b = db.stat().st_size if db.exists() else 0
    wal_b = wal.stat().st_size if wal.exists() else 0
    return {"file_bytes": file_b, "wal_bytes": wal_b, "total_bytes": file_b + wal_b}


def written_rows(db: Path) -> int:
    """Audit rows written so far and applied from the journal (ids are AUTOINCREMENT)."""
    with closing(_ro(db)) as c:
        row = c.execute("SELECT seq FROM sqlite_sequence WHERE name = 'audit'").fetchone()
    return row[0] if row else 0


def table_bytes(db: Path, pages: bool = False) -> dict:
    """Audit rows, and with ``pages`` the bytes of each table and index (dbstat)."""
    with closing(_ro(db)) as c:
        (rows,) = c.execute("SELECT COUNT(*) FROM audit").fetchone()
        out: dict = {"audit_rows": rows}
        if pages:
            out["tables_bytes"] = dict(
                c.execute("SELECT name, SUM(pgsize) FROM dbstat GROUP BY name ORDER BY 2 DESC")
            )
            out["tables_used_bytes"] = dict(
                c.execute("SELECT name, SUM(pgsize - unused) FROM dbstat GROUP BY name")
            )
            (page,) = c.execute("PRAGMA page_size").fetchone()
            (free,) = c.execute("PRAGMA freelist_count").fetchone()
            out["free_bytes"] = page * free
    return out


def _counts(c: sqlite3.Connection) -> tuple[dict[str, int], set[str]]:
    counts = dict(c.execute("SELECT loop_id, COUNT(*) FROM audit GROUP BY loop_id"))
    return counts, {r[0] for r in c.execute("SELECT id FROM loops")}


def settled(db: Path, config, deleted: list[str], timeout: float) -> float:
    """Wait until the retention passes caught up after the load (every registered loop
    within the row cap, every deleted one within its cap); the seconds it took."""
    start = time.monotonic()
    cap = config.history_max_rows_per_loop or float("inf")
    cap_deleted = config.history_max_rows_deleted
    gone = set(deleted)
    while True:
        with closing(_ro(db)) as c:
            counts, registered = _counts(c)
        over = [i for i, n in counts.items() if n > (cap if i in registered else cap_deleted)]
        if not over or not gone:
            return time.monotonic() - start
        if time.monotonic() - start > timeout:
            raise TimeoutError(f"{len(over)} loops still over their row cap after {timeout:.0f} s")
        time.sleep(1.0)


def check(db: Path, archive: Path, config, deleted: list[str], end_wall: float) -> dict:
    """Every row written is kept or archived; none the policy protects was pruned.

    A row is protected at the end of the run when it is younger than the horizon
    (``end_wall`` - max age) and among the newest ``cap`` rows of its loop (the deleted
    loops' cap for a loop deleted by then). Rows only accumulate and ``end_wall`` is at
    or after the tuner's clock when it stopped, so a row pruned lawfully at any pass is
    unprotected at the end: a protected row in the archive is a row lost.
    """
    with closing(_ro(db)) as c:
        kept = c.execute("SELECT id, loop_id, wall_time FROM audit").fetchall()
        (max_id,) = c.execute("SELECT seq FROM sqlite_sequence WHERE name = 'audit'").fetchone()
        counts, registered = _counts(c)
        (page,) = c.execute("PRAGMA page_size").fetchone()
    sizes = {**db_bytes(db), **table_bytes(db, pages=True)}
    pruned = []
    if archive.exists():
        with open(archive, "rb") as f:
            pruned = [(r["id"], r["loop_id"], r["wall_time"]) for r in map(orjson.loads, f)]
    rows = kept + pruned
    ids = np.fromiter((r[0] for r in rows), np.int64, len(rows))
    wall = np.fromiter((r[2] for r in rows), np.float64, len(rows))
    names, loop = np.unique(np.array([r[1] for r in rows], dtype=object), return_inverse=True)
    is_pruned = np.zeros(len(rows), bool)
    is_pruned[len(kept) :] = True
    order = np.lexsort((-ids, loop))  # by loop, newest first
    first = np.searchsorted(loop[order], loop[order], side="left")
    rank = np.empty(len(rows), np.int64)
    rank[order] = np.arange(len(rows)) - first
    cap_of = {True: config.history_max_rows_per_loop, False: config.history_max_rows_deleted}
    caps = np.array([cap_of[n in registered] or np.iinfo(np.int64).max for n in names])
    horizon = (
        -np.inf
        if config.history_max_age_days is None
        else end_wall - config.history_max_age_days * 86400.0
    )
    protected = (wall >= horizon) & (rank < caps[loop])
    all_ids = np.sort(ids)
    complete = bool(len(all_ids) == max_id and np.array_equal(all_ids, np.arange(1, max_id + 1)))
    gone = set(deleted)
    reg_counts = [n for i, n in counts.items() if i in registered]
    del_counts = [counts.get(i, 0) for i in gone]
    audit = ("audit", "audit_loop")
    audit_b = sum(v for k, v in sizes["tables_bytes"].items() if k in audit)
    used_b = sum(v for k, v in sizes["tables_used_bytes"].items() if k in audit)
    per_row = used_b / max(len(kept), 1)
    return {
        "rows": {
            "written": int(max_id),
            "kept": len(kept),
            "pruned": len(pruned),
            "pruned_older_than_horizon": int((is_pruned & (wall < horizon)).sum()),
            "pruned_beyond_cap": int((is_pruned & (rank >= caps[loop])).sum()),
            "protected": int(protected.sum()),
            "protected_lost": int((protected & is_pruned).sum()),
            "kept_plus_pruned_is_every_id": complete,
            "per_registered_loop": _stats(reg_counts),
            "per_site_loop": _stats([n for i, n in counts.items() if i[0] == "S"]),
            "per_fast_loop": _stats([n for i, n in counts.items() if i[0] == "F"]),
            "deleted_loops": len(gone),
            "per_deleted_loop": _stats(del_counts),
            "of_deleted_loops": int(sum(del_counts)),
        },
        "size": {
            **sizes,
            "page_size": page,
            "archive_bytes": archive.stat().st_size if archive.exists() else 0,
            "audit_bytes_per_row": per_row,
            "audit_page_bytes_per_row": audit_b / max(len(kept), 1),
        },
        "horizon_wall": None if horizon == -np.inf else float(horizon),
        "end_wall": end_wall,
    }


def _stats(values: list[int]) -> dict:
    if not values:
        return {"n": 0}
    a = np.asarray(values)
    return {"n": int(a.size), "max": int(a.max()), "mean": float(a.mean()),
            "p50": float(np.median(a))}  # fmt: skip


def budget(config, result: dict) -> dict:
    """The policy's disk budget for the loops of the run, and the verdict."""
    rows, size = result["rows"], result["size"]
    cap = config.history_max_rows_per_loop
    loops = config.loops + config.fast + 1  # and the END marker
    budget_b = None
    if cap is not None:
        policy_rows = loops * cap + rows["deleted_loops"] * config.history_max_rows_deleted
        budget_b = policy_rows * BYTES_PER_ROW + loops * BYTES_PER_LOOP + WAL_ALLOWANCE
    peak = max([t["total_bytes"] for t in result["timeline"]] + [size["total_bytes"]])
    per_row = size["audit_bytes_per_row"]
    year = {}
    for period in RL_PERIODS_S:
        n = YEAR_S / period
        kept = n if cap is None else min(n, cap)
        year[f"{period:g}"] = {"rows_per_year": round(n), "bytes_uncapped": round(n * per_row),
                               "bytes_with_policy": round(kept * per_row)}  # fmt: skip
    checks = {
        "peak_under_budget": budget_b is not None and peak <= budget_b,
        "bytes_per_row_within_allowance": per_row <= BYTES_PER_ROW,
        "nothing_protected_lost": rows["protected_lost"] == 0,
        "every_row_kept_or_archived": rows["kept_plus_pruned_is_every_id"],
        "registered_within_cap": cap is None or rows["per_registered_loop"].get("max", 0) <= cap,
        "deleted_within_cap": rows["per_deleted_loop"].get("max", 0)
        <= config.history_max_rows_deleted,
        "no_sample_lost": result["samples_received"] == result["samples_published"],
        "ran_the_planned_hours": result.get("stopped") == "completed",
    }
    result["verdict"] = {"ok": all(checks.values()), **checks}
    return {
        "formula": "(loops x max_rows_per_loop + deleted x max_rows_deleted) x BYTES_PER_ROW "
        "+ loops x BYTES_PER_LOOP + WAL_ALLOWANCE",
        "bytes_per_row_allowance": BYTES_PER_ROW,
        "bytes_per_loop": BYTES_PER_LOOP,
        "wal_allowance": WAL_ALLOWANCE,
        "loops": loops,
        "budget_bytes": budget_b,
        "peak_bytes": peak,
        "per_loop_year_at_rl_period_s": year,
    }
