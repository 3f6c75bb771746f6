"""The store's journal: gains and audit rows committed as one row before publishing,
applied to the tables later. A process that dies before (or while) applying them loses
nothing, and the audit log keeps the order of events."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from service.daemon.store import Store
from service.engine.audit import audit_row
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body

pytestmark = pytest.mark.timeout(60)
ROOT = Path(__file__).resolve().parents[1]
IDS = [f"L{i}" for i in range(5)]


def _step(seq: int) -> tuple[list, list]:
    """Gains rows and audit rows of one batched step of every loop."""
    gains = [(0.5 + seq + i, 0.01 * seq, seq, loop_id) for i, loop_id in enumerate(IDS)]
    audit = [
        audit_row(loop_id, 100.0 + seq, 10.0 * seq, seq, "auto", "agent", (0.5, 0.01), g[:2])
        for loop_id, g in zip(IDS, gains, strict=True)
    ]
    return gains, audit


def _crash_after(db: Path, code: str) -> None:
    """Run ``code`` with ``store`` open on ``db`` in a child process that then dies
    without closing anything (``os._exit``), as a killed daemon would."""
    script = (
        textwrap.dedent(
            f"""
        import os
        from service.daemon.store import Store
        from tests.test_tuner_journal import _step
        store = Store({str(db)!r})
        """
        )
        + textwrap.dedent(code)
        + "\nos._exit(0)\n"
    )
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=True, timeout=30)


@pytest.fixture
def db(tmp_path) -> Path:
    path = tmp_path / "pitune.db"
    store = Store(path)
    configs = [LoopConfig(**loop_body(i)) for i in IDS]
    store.insert_loops(configs, [audit_row(c.id, 0.0, None, 0, "auto", "registered",
                                           None, (c.kp, c.ki)) for c in configs],
                       [0] * len(configs))  # fmt: skip
    store.close()
    return path


@pytest.mark.parametrize("applied", [0, 3, 7])  # nothing, part of the gains, into the audit
def test_a_crash_before_the_journal_is_applied_loses_nothing(db, applied):
    _crash_after(
        db,
        f"""
        store.record_gains(*_step(1))
        store.record_gains(*_step(2))
        assert store.apply_journal({applied}) == 20 - {applied}
        """,
    )
    store = Store(db)
    try:
        assert store.journal_rows == 20 - applied  # still there after the crash
        loops = {s.config.id: s for s in store.load()}
        assert store.journal_rows == 0
        for i, loop_id in enumerate(IDS):
            assert (loops[loop_id].kp, loops[loop_id].ki, loops[loop_id].seq) == (2.5 + i, 0.02, 2)
            total, items = store.history(loop_id, 0, 10)
            # each row exactly once, even those applied before the crash
            assert total == 3
            assert [(e.reason, e.seq) for e in items] == [
                ("agent", 2), ("agent", 1), ("registered", 0)
            ]  # fmt: skip
    finally:
        store.close()


def test_other_writes_and_history_see_the_journal_in_order(db):
    store = Store(db)
    try:
        store.record_gains(*_step(1))
        assert store.journal_rows == 10
        total, items = store.history("L0", 0, 10)  # a read applies the journal first
        assert total == 2 and items[0].reason == "agent" and store.journal_rows == 0

        store.record_gains(*_step(2))
        config = LoopConfig(**loop_body("L1", mode="advisory"))
        store.update_config(config, audit_row("L1", 300.0, None, 2, "advisory", "patched",
                                              (2.5, 0.02), (2.5, 0.02)))  # fmt: skip
        assert store.journal_rows == 0
        _, items = store.history("L1", 0, 10)
        assert [e.reason for e in items] == ["patched", "agent", "agent", "registered"]
        assert [e.id for e in items] == sorted((e.id for e in items), reverse=True)
    finally:
        store.close()
    store = Store(db)
    try:
        assert store.journal_rows == 0  # close applied what was left
    finally:
        store.close()


def test_commits_before_publishing_reach_the_disk_applying_the_journal_need_not(db):
    """synchronous=FULL (2: fsync at commit) for what a power cut must not take, NORMAL
    (1) for what the journal still holds or a snapshot can lose."""
    store = Store(db)
    try:
        level = store._db.execute  # the level the last commit ran with
        store.record_gains(*_step(1))
        assert level("PRAGMA synchronous").fetchone() == (2,)
        store.apply_journal()
        assert level("PRAGMA synchronous").fetchone() == (1,)
        store.snapshot([("L0", b"", "{}")])
        assert level("PRAGMA synchronous").fetchone() == (1,)
        store.delete_loop("L1", audit_row("L1", 1.0, None, 1, "auto", "deleted", None, None))
        assert level("PRAGMA synchronous").fetchone() == (2,)
    finally:
        store.close()
