"""Issue 18, retention bar at CI scale: the accelerated retention run
(service/bench/retention.py) through the real tuner process, bus and SQLite store, with
a short horizon and small caps so that both rules and the deleted loops' cap act within
two plant hours; the clock that accelerates it; and a prune pass's write-ahead log."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from service.bench.retention import RetentionConfig, execute
from service.daemon.clock import Clock
from service.daemon.store import Store
from service.engine.audit import audit_row

pytestmark = pytest.mark.timeout(180)


def test_two_plant_hours_in_seconds_prune_by_age_and_rows_and_lose_nothing_protected(tmp_path):
    """50 site loops (RL step 55-165 s), 4 fast ones (22 s) and 4 churned every half
    hour, at 360x: horizon 1 h, 200 rows per loop, 10 per deleted loop."""
    config = RetentionConfig(
        loops=50, hours=2.0, speed=360.0, sample_period=10.0, tau=(10.0, 30.0), fast=4,
        fast_tau=4.0, churn=4, churn_every=1800.0, groups=4, report_every=1800.0,
        history_max_rows_per_loop=200, history_max_age_days=1.0 / 24.0,
        history_max_rows_deleted=10, history_prune_interval_s=600.0, workdir=tmp_path,
    )  # fmt: skip
    started = time.monotonic()
    result = execute(config)
    rows, verdict = result["rows"], result["verdict"]
    assert verdict["ok"], verdict
    # counted against what was written: every audit id is kept or in the archive
    assert rows["kept_plus_pruned_is_every_id"]
    assert rows["kept"] + rows["pruned"] == rows["written"] > 5000
    # nothing younger than the horizon and within the cap was pruned, while both rules
    # really pruned (the fast loops' 325 rows exceed the cap, the site's hour-old rows age)
    assert rows["protected_lost"] == 0 and rows["protected"] > 1000
    assert rows["pruned_older_than_horizon"] > 1000 and rows["pruned_beyond_cap"] > 500
    # a fast loop keeps at most its cap; the age rule leaves it about the last plant hour
    # (~160 rows at 22 s, fewer when a pass lands late in the hour or steps were gated)
    assert 100 < rows["per_fast_loop"]["max"] <= 200
    # deleted loops: 4 generations of 4, each down to its cap
    assert rows["deleted_loops"] == 16 and rows["per_deleted_loop"]["max"] <= 10
    # size bounded by the policy's budget, the plant clock kept pace, no sample lost
    assert result["budget"]["peak_bytes"] <= result["budget"]["budget_bytes"]
    assert result["samples_received"] == result["samples_published"] > 40_000
    assert result["samples_rejected"] == 0
    assert result["generator_late_max_s"] < 5.0
    assert [t["plant_h"] for t in result["timeline"]] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert time.monotonic() - started < 150


def test_the_clock_runs_speed_times_real_time():
    real = Clock()
    assert abs(real.wall() - time.time()) < 0.01
    fast = Clock(100.0)
    w0, m0, r0 = fast.wall(), fast.monotonic(), time.monotonic()
    time.sleep(0.05)
    elapsed = time.monotonic() - r0
    assert fast.wall() - w0 == pytest.approx(100.0 * elapsed, rel=0.2)
    assert fast.monotonic() - m0 == pytest.approx(100.0 * elapsed, rel=0.2)
    assert fast.until(fast.monotonic() + 100.0) == pytest.approx(1.0, abs=0.01)
    with pytest.raises(ValueError, match="positive"):
        Clock(0.0)


def test_a_prune_pass_keeps_the_write_ahead_log_small(tmp_path):
    """1,000 loops x 60 rows, interleaved (as steps write them), pruned to 1 row each:
    every page of the table changes, yet the log stays near SQLite's checkpoint size
    (4 MB), where one transaction for the pass wrote ~20 MB."""
    store = Store(tmp_path / "s.db")
    ids = [f"L{i:04d}" for i in range(1000)]
    for k in range(1, 61):
        audit = [audit_row(i, float(k), 1.0 * k, k, "auto", "agent", (0.5, 0.01), (0.5, 0.01),
                           "reason=agent basis=hint dkp=+1.0% dki=+1.0% guard=none")
                 for i in ids]  # fmt: skip
        store.record_gains([(0.5, 0.01, k, i) for i in ids], audit)
    store.apply_journal()
    store._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    assert store.prune(ids, older_than=None, keep_rows=1, keep_rows_deleted=1) == 1000 * 59
    wal = Path(f"{tmp_path / 's.db'}-wal").stat().st_size
    assert wal < 6 << 20, wal
    store.close()
