"""A store over a year (session 40): the epoch never goes backwards by itself, and one
stored by a start with the clock ahead is reset only on the operator's word; retention
prunes by id ranges, in a time budget, and by age only an unbroken run of a loop's
oldest rows (rows written while the clock was set back stay); the write-ahead log is
bounded; a gateway's memory of tuner instances is not."""

from __future__ import annotations

import io
import logging
import sqlite3
import time

import orjson
import pytest

from service.daemon.settings import default_instance_id
from service.daemon.store import WAL_LIMIT_BYTES, EpochAheadError, Store
from service.daemon.store_pg import PgStore
from service.engine.audit import audit_row
from service.engine.config import LoopConfig
from service.gateways.base import GainsInbox, Source
from service.wire.protocol import GainsMessage
from tests.tuner_support import loop_body

pytestmark = pytest.mark.timeout(120)
DAY = 86400.0
NOW = 1_790_000_000.0
"""A wall time (2026) the tests' rows are written around."""


def _row(loop_id: str, wall: float, seq: int, reason: str = "agent"):
    return audit_row(loop_id, wall, float(seq), seq, "auto", reason, (0.5, 0.01), (0.5, 0.01), "{}")


def _register(store: Store, ids: list[str], wall: float) -> None:
    configs = [LoopConfig(**loop_body(i)) for i in ids]
    store.insert_loops(configs, [_row(i, wall, 0, "registered") for i in ids], [0] * len(ids))


def _seqs(store: Store, loop_id: str) -> list[int]:
    return sorted(e.seq for e in store.history(loop_id, 0, 100_000)[1])


def test_rows_written_while_the_clock_was_set_back_are_not_pruned_as_old(tmp_path):
    """A host booted at 2000-01-01 (no RTC) until NTP fixed it 2 h later: the 120 rows of
    those 2 h are minutes old, far under the cap, and stay; they go by age only once the
    rows written before them are older than the horizon (an id prefix)."""
    store = Store(tmp_path / "s.db")
    _register(store, ["A"], NOW - DAY)
    wrong = 946_684_800.0  # 2000-01-01
    store.record_gains([], [_row("A", wrong + 60 * k, k) for k in range(1, 121)])
    store.record_gains([], [_row("A", NOW + k, 200 + k) for k in range(3)])
    policy = {"keep_rows": 10_000, "keep_rows_deleted": 100}
    assert store.prune(["A"], older_than=NOW - 365 * DAY, **policy) == 0
    assert len(_seqs(store, "A")) == 124  # was 4: every row of the wrong clock pruned
    # a year on, the registration row is older than the horizon, and so the rows after it
    # written by the wrong clock: the prefix goes up to the first row of the right clock
    assert store.prune(["A"], older_than=NOW - DAY + 1, **policy) == 121
    assert _seqs(store, "A") == [200, 201, 202]
    store.close()


def test_age_and_row_cap_cut_each_loop_at_one_id_and_keep_its_newest_row(tmp_path):
    store = Store(tmp_path / "s.db")
    _register(store, ["R", "D"], 0.0)
    for k in range(1, 61):  # a row a day for 60 days, the two loops interleaved
        store.record_gains([], [_row("R", k * DAY, k), _row("D", k * DAY, k)])
    store.delete_loop("D", _row("D", 61 * DAY, 60, "deleted"))
    n = store.prune(["R", "D"], older_than=40 * DAY + 1, keep_rows=30, keep_rows_deleted=3)
    assert _seqs(store, "R") == list(range(41, 61))  # younger than the horizon
    assert _seqs(store, "D") == [59, 60, 60]  # the newest 3 of a deleted loop
    assert n == 41 + 59
    assert store.prune(["R"], older_than=1e12, keep_rows=None, keep_rows_deleted=None) == 19
    assert _seqs(store, "R") == [60]  # the age never takes the newest row
    assert store.prune(["R", "D"], older_than=1e12, keep_rows=1, keep_rows_deleted=1) == 2
    store.close()


def test_a_budgeted_prune_takes_only_the_ids_it_gets_to(tmp_path):
    """The worker prunes for PRUNE_BUDGET_S an iteration: the ids it did not get to stay
    in the iterator for the next one (a budget of 0: one id a call)."""
    store = Store(tmp_path / "s.db")
    ids = [f"L{i}" for i in range(5)]
    _register(store, ids, NOW)
    store.record_gains([], [_row(i, NOW + k, k) for k in range(1, 11) for i in ids])
    todo = iter(ids)
    done = [store.prune(todo, older_than=None, keep_rows=4, keep_rows_deleted=1, budget_s=0.0)]
    assert done == [7] and next(todo) == "L1"  # L0 pruned, L1 not taken from the iterator
    assert [len(_seqs(store, i)) for i in ids] == [4, 11, 11, 11, 11]
    store.close()


def test_a_pass_lists_its_loop_ids_by_a_step_per_loop_not_per_row(tmp_path):
    """The loop ids of a retention pass (taken under the store's lock at each pass's
    start): SELECT DISTINCT read every audit row's index entry (176-355 ms at 2 M rows)."""
    store = Store(tmp_path / "s.db")
    ids = [f"L{i:02d}" for i in range(20)]
    _register(store, ids, NOW)
    store.record_gains([], [_row(i, NOW + k, k) for k in range(1, 501) for i in ids])
    store.delete_loop("L07", _row("L07", NOW + 600, 500, "deleted"))
    store.apply_journal()
    steps = []
    store._db.set_progress_handler(lambda: steps.append(1), 100)
    assert store.audit_ids() == ids
    assert store.audit_ids(deleted_only=True) == ["L07"]
    store._db.set_progress_handler(None, 100)
    assert len(steps) < 30  # 15; reading all 10,020 rows was 912 (of 100 instructions)
    store.close()


def _gateway_takes(epoch: int) -> bool:
    """Whether a gateway on the right clock that took an update at NOW takes ``epoch``'s."""
    inbox = GainsInbox()
    for seq, e in ((5, int(NOW * 1000)), (1, epoch)):
        msg = GainsMessage(loop_id="L", seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=0.5, ki=0.02,
                           mode="auto", instance_id="x", epoch=e)  # fmt: skip
        inbox.put_raw(Source.gains, msg.model_dump_json().encode())
    return [u.seq for u in inbox.drain()] == [5, 1]


def test_a_start_with_the_clock_behind_never_lowers_the_epoch(tmp_path, caplog):
    """A start with the host clock 2 days behind (RTC reset, NTP not synced) took the
    clock (a lower epoch) and every gateway dropped its gains as stale: it is refused
    now, leaving the epoch as it was; a running member's lease continues the epoch."""
    store = Store(tmp_path / "s.db")
    first = store.next_epoch(NOW)
    with pytest.raises(EpochAheadError, match="48.0 h ahead of the clock"):
        store.next_epoch(NOW - 2 * DAY)
    assert store.next_epoch(NOW - 2 * DAY, "keep") == first + 1
    assert store.next_epoch(NOW - 3600.0) == first + 2  # within a day: still only grows
    assert _gateway_takes(first + 2)
    assert "EPOCH RESET" not in caplog.text
    store.close()


def test_an_epoch_far_ahead_is_reset_only_on_the_operator_s_word(tmp_path, caplog):
    """A start with the clock 3 days ahead stored its epoch, which every gateway on a
    right clock drops: only the operator's PITUNE_EPOCH_RESET starts again from the
    clock (with an ERROR); after it the epoch grows again."""
    store = Store(tmp_path / "s.db")
    assert store.next_epoch(NOW + 3 * DAY) == int((NOW + 3 * DAY) * 1000)
    with pytest.raises(EpochAheadError, match="72.0 h ahead"):
        store.next_epoch(NOW)
    with caplog.at_level(logging.ERROR, logger="pitune.store"):
        assert store.next_epoch(NOW, "reset") == int(NOW * 1000)
    assert "EPOCH RESET (PITUNE_EPOCH_RESET)" in caplog.text and "72.0 h ahead" in caplog.text
    assert store.next_epoch(NOW - 3600.0) == int(NOW * 1000) + 1
    assert _gateway_takes(int(NOW * 1000) + 1)
    store.close()


def test_a_cluster_s_epoch_follows_the_database_clock(pg_url, caplog):
    """One member's wrong clock (2 days behind, 10 days ahead) moves the shared epoch
    neither back nor far ahead: the epoch is taken on the database's clock."""
    store = PgStore(pg_url)
    try:
        first = store.next_epoch(time.time())
        assert store.next_epoch(time.time() - 2 * DAY) > first  # a member's clock behind
        epoch = store.next_epoch(time.time() + 10 * DAY)  # a member's clock ahead
        assert epoch < (store.wall_now() + 60.0) * 1000
        with store.transaction() as db:  # an epoch stored 3 days ahead of the database
            db.execute(
                "UPDATE meta SET value = %s WHERE key = 'epoch'", (str(epoch + 3 * 86_400_000),)
            )
        with pytest.raises(EpochAheadError, match="72.0 h ahead"):
            store.next_epoch(time.time() + 10 * DAY)  # no member's clock lets it through
        clock = int(store.wall_now() * 1000)  # (as next_epoch takes it)
        with caplog.at_level(logging.ERROR, logger="pitune.store"):
            reset = store.next_epoch(0.0, "reset")
        # from the database's clock again (not above the earlier epoch: those of calls
        # within one millisecond run a step or two ahead of the clock, CI saw them equal)
        assert clock <= reset < (store.wall_now() + 60.0) * 1000 < epoch + 3 * 86_400_000
        assert "EPOCH RESET" in caplog.text
    finally:
        store.close()


def _put(inbox: GainsInbox, loop_id: str, epoch: int | None, seq: int, instance: str) -> None:
    msg = GainsMessage(loop_id=loop_id, seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=0.5, ki=0.02,
                       mode="auto", instance_id=instance, epoch=epoch)  # fmt: skip
    inbox.put_raw(Source.gains, msg.model_dump_json().encode())


def test_a_gateway_logs_implausible_epochs_once_a_minute(caplog):
    """Gains dropped for an epoch ahead of the gateway's clock were only counted: the
    loops went untuned with nothing in any log."""
    inbox = GainsInbox()
    with caplog.at_level(logging.ERROR, logger="pitune.gateway"):
        for seq in range(1, 4):
            _put(inbox, "L", int(time.time() * 1000) + 3 * 86_400_000, seq, "ahead")
        assert inbox.drain() == []
    assert inbox.implausible == 3
    assert len([r for r in caplog.records if "DROPPED" in r.message]) == 1
    assert "72.0 h ahead" in caplog.text


def test_the_wal_is_bounded_and_emptied_after_a_reader_held_a_snapshot(tmp_path):
    """A reader holding a snapshot (a backup, an export) keeps every write in the WAL; the
    file kept its peak size for ever (241 MB). Now cut back to WAL_LIMIT_BYTES when the
    log restarts, and emptied by the checkpoint that ends a retention pass."""
    path = tmp_path / "s.db"
    store = Store(path)
    assert store._db.execute("PRAGMA journal_size_limit").fetchone() == (WAL_LIMIT_BYTES,)
    _register(store, ["A"], NOW)
    reader = sqlite3.connect(path)
    reader.execute("BEGIN")
    reader.execute("SELECT count(*) FROM audit").fetchone()
    detail = orjson.dumps({"note": "x" * 2000}).decode()
    for k in range(30):
        rows = [audit_row("A", NOW, 0.0, k * 100 + j, "auto", "agent", None, None, detail)
                for j in range(100)]  # fmt: skip
        store.record_gains([], rows)
        store.apply_journal()
    wal = tmp_path / "s.db-wal"
    grown = wal.stat().st_size
    assert grown > 4 << 20
    store.checkpoint()  # the reader still holds its snapshot: no wait, nothing lost
    assert _seqs(store, "A")[-1] == 2999
    reader.rollback()
    reader.close()
    store.checkpoint()
    assert wal.stat().st_size == 0  # was kept at its peak
    store.close()


def test_an_export_reads_in_chunks_of_ids_and_holds_no_snapshot(tmp_path, monkeypatch):
    """An export reads EXPORT_CHUNK rows per query, each its own read transaction: every
    row once, in id order, one loop's or all; rows committed while it runs are in its
    later chunks (one query for all held one snapshot, and the WAL grew meanwhile)."""
    from service.daemon import retention_store

    monkeypatch.setattr(retention_store, "EXPORT_CHUNK", 7)
    path = tmp_path / "s.db"
    store = Store(path)
    _register(store, ["A", "B"], NOW)
    store.record_gains([], [_row(i, NOW + k, k) for k in range(1, 21) for i in ("A", "B")])
    store.apply_journal()

    class Out(io.BytesIO):
        def write(self, data: bytes) -> int:
            if not self.tell():  # a writer commits while the export runs
                with sqlite3.connect(path) as writer:
                    writer.executemany(
                        "INSERT INTO audit (loop_id, wall_time, seq, mode, reason) "
                        "VALUES ('A', 0.0, ?, 'auto', 'agent')",
                        [(100 + k,) for k in range(5)],
                    )
            return super().write(data)

    out = Out()
    assert store.export(out) == 47
    rows = [orjson.loads(line) for line in out.getvalue().splitlines()]
    assert [r["id"] for r in rows] == list(range(1, 48))
    out = io.BytesIO()
    assert store.export(out, "B", since_id=10) == 16
    assert {orjson.loads(line)["loop_id"] for line in out.getvalue().splitlines()} == {"B"}
    store.close()


def test_a_gateway_forgets_the_instances_of_tuners_with_epochs():
    inbox = GainsInbox()
    now_ms = int(time.time() * 1000)

    def put(loop_id: str, epoch: int | None, seq: int, instance: str) -> None:
        _put(inbox, loop_id, epoch, seq, instance)

    for restart in range(100):  # 100 tuner restarts of 20 loops, each a new instance id
        for i in range(20):
            put(f"L{i}", now_ms + restart, 1, f"tuner-{restart}")
        assert len(inbox.drain()) == 20
    assert len(inbox._last) == 0  # was 2,000: an entry per (loop, instance) for ever
    put("L0", None, 1, "rev1")  # a tuner of revision 1 (no epoch): judged by its seqs
    put("L0", None, 1, "rev1")
    assert len(inbox.drain()) == 1 and inbox.stale == 1


def test_a_forged_instance_id_is_invalid_and_forges_no_gateway_log_line(caplog):
    """The gateway's implausible-epoch ERROR named the message's instance_id raw: one with
    a newline forged a line of the gateway host's log. Instance ids are ids now (the
    tuner's own, host-pid, are), and the line shows the id with repr."""
    evil = "t1\n2026-12-05 06:00:00,000 INFO pitune.gateway: all gains applied"
    body = dict(loop_id="L1", seq=1, t=0.0, dkp=0.0, dki=0.0, kp=1.0, ki=1.0, mode="auto")
    inbox = GainsInbox()
    with caplog.at_level(logging.ERROR, logger="pitune.gateway"):
        inbox.put_raw(Source.gains, orjson.dumps({**body, "instance_id": evil, "epoch": 2**62}))
        inbox.put_raw(Source.gains, orjson.dumps({**body, "instance_id": "t-2", "epoch": 2**62}))
        assert inbox.drain() == [] and (inbox.invalid, inbox.implausible) == (1, 1)
    (line,) = [r.getMessage() for r in caplog.records]
    assert "from 't-2' DROPPED" in line and "\n" not in line
    assert GainsMessage(**body, instance_id=default_instance_id()).instance_id
