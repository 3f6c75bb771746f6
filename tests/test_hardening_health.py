"""A stuck or failing tuner looks unhealthy (review of operability, session 39).

A worker blocked on a PostgreSQL table lock (a DBA's VACUUM FULL / ALTER TABLE) kept
/healthz at 200 and hung /metrics; snapshot writes failing on a full disk were logged
as a traceback each and nowhere else. Now: the store's statements give up on a lock
after LOCK_TIMEOUT_S (a store failure: /healthz 503), a worker stuck in one iteration
past ``store_failure_exit_s`` is a 503 too, /metrics answers while the worker holds the
loop table, and failing snapshot/journal writes are a 503, counted, logged once.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time

import httpx
import psycopg
import pytest
import zenoh

from service.daemon.admin import METRICS_LOCK_WAIT_S
from service.daemon.api import healthz, metrics
from service.daemon.delivery import COMMIT_RETRY_S
from service.daemon.store_pg import LOCK_TIMEOUT_S
from service.daemon.tuner import Tuner
from service.engine.config import Registration
from service.procs import TunerProcess
from service.wire.session import session_config
from tests.tuner_support import connected_gateway, loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(180)


def _metric(text: str, name: str) -> float:
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(name))


def _feed(endpoint: str, ids: list[str], stop: threading.Event) -> threading.Thread:
    """Samples of a square-wave error for ``ids`` until ``stop`` (the loops step)."""

    def run() -> None:
        with zenoh.open(session_config(mode="peer", connect=[endpoint])) as gw:
            i = 0
            while not stop.wait(0.01):
                e = 1.0 if (i // 50) % 2 else -1.0
                for loop_id in ids:
                    gw.put(f"pitune/loops/{loop_id}/sample", json.dumps({"t": float(i), "e": e}))
                i += 1

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_table_lock_makes_healthz_fail_and_metrics_still_answer(tmp_path, pg_url):
    tuner = TunerProcess(pg_url, "--agent-weights", "untrained", log=tmp_path / "tuner.log",
                         env={"PITUNE_MAX_SAMPLE_RATE_HZ": "1000", "PITUNE_INSTANCE_ID": "m1",
                              "PITUNE_STORE_FAILURE_EXIT_S": "120"})  # fmt: skip
    tuner.start()
    stop = threading.Event()
    try:
        c = tuner.http()
        ids = [f"L{i}" for i in range(3)]
        body = [loop_body(i, guard={"identify": False}) for i in ids]
        c.post("/loops/bulk", json=body).raise_for_status()
        _feed(tuner.zenoh, ids, stop)
        wait_until(lambda: _metric(c.get("/metrics").text, "pitune_updates_published_total"),
                   timeout=60.0, what="a first step committed")  # fmt: skip
        dba = psycopg.connect(pg_url)  # a transaction: the lock held until the rollback
        dba.execute("LOCK TABLE audit IN ACCESS EXCLUSIVE MODE")
        locked = time.monotonic()
        try:
            # the next step's commit waits LOCK_TIMEOUT_S, then fails like any store error
            h = wait_until(lambda: (r := c.get("/healthz")).status_code == 503 and r,
                           timeout=LOCK_TIMEOUT_S + 30.0, what="/healthz 503")  # fmt: skip
            assert "lock timeout" in h.json()["detail"], h.json()
            assert h.json()["status"] == "failing"
            began = time.monotonic()
            m = httpx.get(f"{tuner.api}/metrics", timeout=METRICS_LOCK_WAIT_S + 5.0)
            assert m.status_code == 200 and time.monotonic() - began < METRICS_LOCK_WAIT_S + 5.0
            assert _metric(m.text, "pitune_store_commit_failures_total") >= 1
            assert "pitune_worker_heartbeat_age_seconds" in m.text
            assert c.get("/readyz").status_code == 503
            assert time.monotonic() - locked < 120  # the tuner did not exit meanwhile
        finally:
            dba.rollback()
            dba.close()
        wait_until(lambda: c.get("/healthz").status_code == 200,
                   timeout=30.0, what="/healthz 200 again")  # fmt: skip
        assert tuner.proc.running
    finally:
        stop.set()
        tuner.stop()


def test_failing_snapshot_writes_make_healthz_fail_and_count(tmp_path):
    db = tmp_path / "pitune.db"
    tuner = TunerProcess(db, "--agent-weights", "untrained", log=tmp_path / "tuner.log",
                         env={"PITUNE_SNAPSHOT_INTERVAL_S": "0.5"})  # fmt: skip
    tuner.start()
    try:
        c = tuner.http()
        c.post("/loops/bulk", json=[loop_body(f"L{i}") for i in range(3)]).raise_for_status()
        assert c.get("/healthz").status_code == 200
        # Every snapshot write now fails in the store (as on a full disk: an error from
        # the commit), until the trigger goes.
        with sqlite3.connect(db) as conn:
            for op in ("INSERT", "UPDATE"):
                conn.execute(f"CREATE TRIGGER full_{op} BEFORE {op} ON snapshots "
                             "BEGIN SELECT RAISE(ABORT, 'no space left'); END")  # fmt: skip
        h = wait_until(lambda: (r := c.get("/healthz")).status_code == 503 and r,
                       timeout=30.0, what="/healthz 503")  # fmt: skip
        assert h.json()["status"] == "failing"
        assert "store writes failing" in h.json()["detail"], h.json()
        assert "no space left" in h.json()["detail"]
        failures = wait_until(
            lambda: _metric(c.get("/metrics").text, "pitune_store_write_failures_total") >= 3
            and _metric(c.get("/metrics").text, "pitune_store_write_failures_total"),
            timeout=30.0, what="three failed snapshot writes",
        )  # fmt: skip
        assert failures >= 3
        assert c.get("/readyz").status_code == 200  # commits still work: it tunes
        with sqlite3.connect(db) as conn:
            for op in ("INSERT", "UPDATE"):
                conn.execute(f"DROP TRIGGER full_{op}")
        wait_until(lambda: c.get("/healthz").status_code == 200,
                   timeout=30.0, what="/healthz 200 again")  # fmt: skip
        log = tuner.log.read_text()
        assert log.count("store writes failing") == 1, log  # one error per outage
        assert "Traceback" not in log
        assert log.count("store writes work again") == 1
    finally:
        tuner.stop()


def test_a_worker_stuck_in_one_iteration_makes_healthz_fail(tmp_path):
    settings = tuner_settings(tmp_path, store_failure_exit_s=1.0)
    with Tuner(settings) as tuner:
        tuner.register(Registration.model_validate(loop_body()))
        gw = connected_gateway(settings)
        try:
            held, release = threading.Event(), threading.Event()

            def hold() -> None:  # another thread: the lock is re-entrant for this one
                with tuner.table.lock:
                    held.set()
                    release.wait(60.0)

            holder = threading.Thread(target=hold, daemon=True)
            holder.start()
            held.wait(10.0)
            try:  # the worker blocks on the table at its next sample
                gw.send("LIC-101", {"t": 0.0, "e": 0.5})
                wait_until(lambda: tuner.heartbeat.age() > settings.store_failure_exit_s,
                           timeout=30.0, what="the worker stuck")  # fmt: skip
                response = healthz(tuner)
                assert response.status_code == 503
                assert b"worker stuck in one iteration" in response.body
                began = time.monotonic()
                scrape = metrics(tuner)  # does not wait for the table
                assert time.monotonic() - began < METRICS_LOCK_WAIT_S + COMMIT_RETRY_S
                age = [
                    line for line in scrape.body.decode().splitlines()
                    if line.startswith("pitune_worker_heartbeat_age_seconds ")
                ]  # fmt: skip
                assert float(age[0].split()[-1]) > settings.store_failure_exit_s
            finally:
                release.set()
                holder.join(10.0)
            wait_until(lambda: tuner.heartbeat.age() == 0.0, timeout=10.0, what="idle again")
            assert healthz(tuner).status == "ok"
        finally:
            gw.close()
