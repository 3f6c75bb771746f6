"""A cluster member's reload of loops changed through the store (a NOTIFY: Ownership.
reload_loops) reads the store outside the table's lock; a loop deleted through the
member during that read must not come back from the older read. Real PostgreSQL."""

from __future__ import annotations

import threading

import psycopg
import pytest

from service.daemon.store_pg import CHANNEL
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings

pytestmark = pytest.mark.timeout(60)


def test_a_loop_deleted_during_a_reloads_read_is_not_restored_by_it(tmp_path, pg_url):
    tuner = Tuner(tuner_settings(tmp_path, db_path=pg_url, instance_id="a")).start()
    try:
        tuner.register_many([LoopConfig(**loop_body(f"L{i}")) for i in range(3)])
        read, reloaded, deleted = threading.Event(), threading.Event(), threading.Event()
        restored: list[str] = []
        load, reload, restore = tuner.store.load, tuner.reload_loops, tuner._restore_many

        def load_then_delete(ids=None, **kw):
            rows = load(ids=ids, **kw)
            if ids and "L1" in ids and not read.is_set():  # the stale read: L1 still there
                read.set()
                threading.Thread(target=lambda: (tuner.delete("L1"), deleted.set())).start()
                assert deleted.wait(30.0)
            return rows

        def reload_and_tell(ids):
            reload(ids)
            if read.is_set():
                reloaded.set()

        def restore_and_note(stored, wall, saved=None):
            restored.extend(loop.config.id for loop in stored)
            return restore(stored, wall, saved)

        tuner.store.load, tuner.reload_loops = load_then_delete, reload_and_tell
        tuner._restore_many = restore_and_note
        with psycopg.connect(pg_url, autocommit=True) as conn:  # as another member's patch
            conn.execute(f"NOTIFY {CHANNEL}, 'L1'")
        assert reloaded.wait(30.0)
        assert "L1" not in restored and "L1" not in tuner.loop_ids()
        assert {"L0", "L2"} <= set(tuner.loop_ids())
    finally:
        tuner.store.load = load
        tuner.stop()
