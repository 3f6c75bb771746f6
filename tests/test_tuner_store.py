"""The store across restarts: what it holds must load again, and a row that does not
must not keep the daemon from tuning every other loop."""

import json
import logging
import sqlite3
import threading

import pytest
from fastapi.testclient import TestClient

from service.daemon.api import create_app
from service.daemon.bus import Kind
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.wire.protocol import MAX_MAGNITUDE, UpdateReason
from tests.tuner_support import (
    connected_gateway,
    loop_body,
    snapshot_of,
    tuner_settings,
    wait_until,
)

pytestmark = pytest.mark.timeout(60)
TINY = {"k_hat": 1e-6, "tau_hat": 1e-6}
"""A scaling whose default ki_max (50 agent units) is 1.25e13 per second."""


def test_derived_bounds_are_clamped_to_the_largest_gain():
    config = LoopConfig(**loop_body(scaling=TINY))
    assert config.guard.ki_max == MAX_MAGNITUDE
    assert LoopConfig.model_validate_json(config.model_dump_json()) == config


def test_a_registration_with_an_extreme_scaling_survives_a_restart(tmp_path):
    settings = tuner_settings(tmp_path)
    with TestClient(create_app(settings)) as client:
        # the paper's initial gains (0.05 agent units) and a sample period within the hinted
        # tau: a registration the API's sanity rules accept (docs/tuner.md)
        body = loop_body("TINY", kp=2.5e4, ki=1.25e10, sample_period_s=1e-6, scaling=TINY)
        assert client.post("/loops", json=body).status_code == 201
    with TestClient(create_app(settings)) as client:
        assert client.get("/loops/TINY").json()["config"]["guard"]["ki_max"] == MAX_MAGNITUDE


def test_a_stored_row_that_fails_to_parse_is_skipped_loudly_and_kept(tmp_path, caplog):
    settings = tuner_settings(tmp_path)
    with TestClient(create_app(settings)) as client:
        for loop_id in ("GOOD", "BAD"):
            assert client.post("/loops", json=loop_body(loop_id)).status_code == 201
    with sqlite3.connect(settings.db_path) as db:  # as an older version could write it
        (config,) = db.execute("SELECT config FROM loops WHERE id = 'BAD'").fetchone()
        bad = json.loads(config)
        bad["guard"]["ki_max"] = 1.25e13
        db.execute("UPDATE loops SET config = ? WHERE id = 'BAD'", (json.dumps(bad),))
    caplog.set_level(logging.ERROR, logger="pitune.store")
    with TestClient(create_app(settings)) as client:
        assert client.get("/loops/GOOD").status_code == 200
        assert client.get("/loops/BAD").status_code == 404
        assert "pitune_loops_unloadable 1.0" in client.get("/metrics").text
        r = client.post("/loops", json=loop_body("BAD"))
        assert r.status_code == 409 and "failed to load" in r.json()["detail"]
        assert r.json()["gateways"] == {"BAD": None}  # its stored shard: no gateway
    assert any("'BAD' NOT LOADED" in r.getMessage() for r in caplog.records)
    with sqlite3.connect(settings.db_path) as db:
        assert db.execute("SELECT config FROM loops WHERE id = 'BAD'").fetchone() == (
            json.dumps(bad),
        )


def test_a_snapshot_racing_a_delete_and_a_new_registration_writes_no_stale_state(tmp_path):
    with Tuner(tuner_settings(tmp_path)) as tuner:
        for loop_id in ("A", "B", "C"):
            tuner.register(LoopConfig(**loop_body(loop_id)))
        tuner._handle([(Kind.sample, tuner.keys.sample(i), b'{"t": 5.0, "e": 1.0}') for i in "ABC"])
        write = tuner.store.snapshot

        def racing_write(rows):
            """The API deletes A and registers it again, and deletes B, while the rows of
            the chunk wait to be written (it may do so only once the table is free)."""

            def api():
                tuner.delete("A")
                tuner.register(LoopConfig(**loop_body("A")))
                tuner.delete("B")

            calls = threading.Thread(target=api)
            calls.start()
            calls.join(timeout=0.5)
            write(rows)
            racing.append(calls)

        racing: list[threading.Thread] = []
        tuner.store.snapshot = racing_write
        tuner._snapshot_todo = ["A", "B", "C"]
        tuner._snapshot_some()
        racing[0].join(timeout=5.0)
        tuner.store.snapshot = write
        with sqlite3.connect(tuner.settings.db_path) as db:
            rows = dict(db.execute("SELECT id, runtime FROM snapshots"))
        assert json.loads(rows["C"])["last_t"] == 5.0  # the chunk was written
        assert "A" not in rows and "B" not in rows  # the new A has no old state
        assert tuner.view("A").last_sample_t is None


def test_a_failing_commit_publishes_nothing_loses_nothing_and_is_retried(tmp_path):
    settings = tuner_settings(tmp_path)
    app = create_app(settings)
    with TestClient(app) as client:
        tuner = app.state.tuner
        gw = connected_gateway(settings)
        try:
            client.post("/loops", json=loop_body("LIC-101"))
            record, failures = tuner.store.record_gains, []

            def disk_full(gains, audit):
                failures.append(len(audit))
                raise sqlite3.OperationalError("database or disk is full")

            tuner.store.record_gains = disk_full  # the store fails, in-process
            for i in range(170):  # one RL step due at t = 165
                gw.send("LIC-101", {"t": float(i), "e": 2.0})
            wait_until(lambda: failures, what="a failed commit")
            for path in ("/healthz", "/readyz"):
                r = client.get(path)
                assert r.status_code == 503 and "disk is full" in r.json()["detail"], path
            assert client.post("/loops/LIC-101/reset").status_code == 503
            # the table holds the uncommitted step: no state reply hands it out, and no
            # snapshot stores its agent state beside the older committed gains
            assert list(gw.session.get(settings.keys.state("LIC-101"), timeout=1.0)) == []
            tuner.snapshot()
            assert snapshot_of(settings.db_path, "LIC-101") is None
            for i in range(170, 340):  # another due period: no step on unpublished gains
                gw.send("LIC-101", {"t": float(i), "e": 2.0})
            wait_until(lambda: tuner.metrics.value("pitune_steps_skipped_total") == 1)
            assert tuner.metrics.value("pitune_store_commit_failures_total") >= 1

            assert gw.gains.empty(), "published before it was committed"
            tuner.store.record_gains = record  # the disk has room again
            msg = gw.next_gains(timeout=5.0)  # retried within COMMIT_RETRY_S, then published
            assert (msg.seq, msg.t) == (1, 165.0)
            assert client.get("/healthz").status_code == 200
            items = client.get("/loops/LIC-101/history").json()["items"]
            assert [(e["reason"], e["seq"]) for e in items] == [("agent", 1), ("registered", 0)]
            assert client.get("/loops/LIC-101").json()["kp"] == msg.kp
            ok, state = gw.state("LIC-101")  # committed: answered again
            assert ok and (state["seq"], state["kp"]) == (1, msg.kp)
            # The control: a reset on the same path comes right after that one message; had
            # the uncommitted step been published during the failure, seq 1 came twice.
            assert client.post("/loops/LIC-101/reset").status_code == 200
            control = gw.next_gains()
            assert (control.seq, control.reason) == (2, UpdateReason.reset), "seq 1 went twice"
        finally:
            gw.close()
