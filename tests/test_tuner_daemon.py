"""``pitune tuner`` as a real subprocess: SIGKILL loses nothing, SIGTERM shuts down cleanly."""

import signal
import sqlite3
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.procs import ROOT, TunerProcess, clean_env, pitune
from tests.tuner_support import Gateway, loop_body, open_peer, snapshot_of, wait_until

pytestmark = pytest.mark.timeout(120)
TOKEN = "daemon-token"


def tuner(tmp_path: Path, *args: str, **env: str) -> TunerProcess:
    """An untrained tuner with instance id ``proc``, its database in ``state/``."""
    return TunerProcess(
        tmp_path / "state" / "pitune.db", "--agent-weights", "untrained", "--instance-id", "proc",
        *args, log=tmp_path / "daemon.log", token=TOKEN, env=env,
    )  # fmt: skip


@pytest.fixture
def daemon(tmp_path):
    d = tuner(tmp_path, "--snapshot-interval", "0.2", PITUNE_MAX_SAMPLE_RATE_HZ="1e6")
    try:
        yield d
    finally:
        d.stop()


def test_sigkill_loses_no_loop_and_no_audit_entry_and_tuning_resumes(daemon):
    proc = daemon.start()
    with daemon.http() as api:
        assert api.post("/loops", json=loop_body("LIC-101")).status_code == 201
        assert httpx.post(f"{daemon.api}/loops", json=loop_body("X")).status_code == 401
    gw = Gateway(open_peer([daemon.zenoh]))
    try:
        wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
        for i in range(400):
            gw.send("LIC-101", {"t": float(i), "e": 1.0})
        assert [gw.next_gains().seq for _ in range(2)] == [1, 2]
        wait_until(
            lambda: (snap := snapshot_of(daemon.db, "LIC-101")) and snap[1]["last_t"] == 399.0,
            what="a snapshot after the last sample",
        )
        for i in range(400, 500):
            gw.send("LIC-101", {"t": float(i), "e": 1.0})
        last = gw.next_gains()  # committed before it was published: it must survive
        assert last.seq == 3
        assert proc.signal(signal.SIGKILL) == -signal.SIGKILL
    finally:
        gw.close()

    hidden, runtime = snapshot_of(daemon.db, "LIC-101")
    assert np.linalg.norm(hidden) > 0
    proc = daemon.start()
    with daemon.http() as api:
        view = api.get("/loops/LIC-101").json()
        history = api.get("/loops/LIC-101/history").json()
    assert (view["kp"], view["ki"], view["seq"]) == (last.kp, last.ki, 3)
    assert view["hidden_norm"] == pytest.approx(float(np.linalg.norm(hidden)), rel=1e-6)
    assert view["last_sample_t"] == runtime["last_t"]
    assert [(e["reason"], e["seq"]) for e in history["items"]] == [
        ("agent", 3), ("agent", 2), ("agent", 1), ("registered", 0),
    ]  # fmt: skip

    gw = Gateway(open_peer([daemon.zenoh]))
    try:
        wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
        start = int(runtime["last_t"]) + 1
        due = runtime["next_due"]
        for i in range(start, int(due) + 1):
            gw.send("LIC-101", {"t": float(i), "e": 1.0})
        resumed = gw.next_gains()
        assert (resumed.seq, resumed.t) == (4, due)
        assert resumed.kp - resumed.dkp == pytest.approx(last.kp)  # continues from seq 3
    finally:
        gw.close()
    assert proc.signal(signal.SIGTERM) == 0


def test_sigterm_snapshots_closes_the_session_and_exits_zero(tmp_path):
    d = tuner(tmp_path, "--snapshot-interval", "3600", "--prefix", "site1/pitune")
    try:
        proc = d.start()
        with d.http() as api:
            api.post("/loops", json=loop_body("FIC-7"))
        gw = Gateway(open_peer([d.zenoh]), keys=None)
        try:
            from service.wire.protocol import Keys

            gw.keys = Keys("site1/pitune")
            alive = "site1/pitune/tuners/proc"
            wait_until(lambda: list(gw.session.liveliness().get(alive, timeout=1.0)))
            for i in range(10):
                gw.send("FIC-7", {"t": float(i), "e": 0.5})
            with d.http() as api:
                wait_until(lambda: api.get("/loops/FIC-7").json()["counters"]["samples"] == 10)
            assert snapshot_of(d.db, "FIC-7") is None  # no periodic snapshot yet
            assert proc.signal(signal.SIGTERM) == 0
            assert not list(gw.session.liveliness().get(alive, timeout=1.0))
        finally:
            gw.close()
        hidden, runtime = snapshot_of(d.db, "FIC-7")
        assert runtime["last_t"] == 9.0 and runtime["counters"][0] == 10
        assert "tuner proc stopped" in d.log.read_text()
    finally:
        d.stop()


def test_invalid_settings_exit_with_status_2(tmp_path):
    argv = ["tuner", "--prefix", "a//b", "--db", str(tmp_path / "x")]
    proc = subprocess.run(
        pitune(*argv), cwd=ROOT, env=clean_env(), capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2
    assert "invalid settings" in proc.stderr and "key prefix" in proc.stderr


def test_a_store_that_keeps_failing_makes_the_daemon_exit_for_a_restart(tmp_path):
    """A database locked by another process: no gains go out, and after
    store_failure_exit_s the daemon exits (74) and restarts from what was published."""
    d = tuner(tmp_path, PITUNE_MAX_SAMPLE_RATE_HZ="1e6", PITUNE_STORE_FAILURE_EXIT_S="1")
    try:
        proc = d.start()
        with d.http() as api:
            assert api.post("/loops", json=loop_body("LIC-101")).status_code == 201
        gw = Gateway(open_peer([d.zenoh]))
        locker = sqlite3.connect(d.db, isolation_level=None)
        try:
            wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
            locker.execute("BEGIN IMMEDIATE")  # holds the write lock
            for i in range(170):
                gw.send("LIC-101", {"t": float(i), "e": 1.0})
            assert proc.wait(60) == 74  # two 5 s busy timeouts, 1 s apart
            assert gw.gains.empty()
        finally:
            locker.close()
            gw.close()
        assert "exiting for a supervisor to restart the tuner" in d.log.read_text()
        d.start()
        with d.http() as api:
            assert api.get("/loops/LIC-101").json()["seq"] == 0  # nothing was published
            items = api.get("/loops/LIC-101/history").json()["items"]
            assert [e["reason"] for e in items] == ["registered"]
    finally:
        d.stop()


def test_a_local_client_cannot_choose_the_address_the_log_records(daemon):
    """uvicorn's default believed X-Forwarded-For from any client on loopback; the tuner
    believes only the proxies of api_trusted_proxies (none by default)."""
    daemon.start()
    with daemon.http() as client:
        r = client.post("/loops", json=loop_body("L1"), headers={"X-Forwarded-For": "10.66.66.66"})
        assert r.status_code == 201, r.text

    def logged() -> str | None:
        lines = daemon.log.read_text().splitlines()
        return next((x for x in lines if "'L1' registered" in x), None)

    line = wait_until(logged, 30.0, "the registration's log line")
    assert "from 127.0.0.1" in line and "10.66.66.66" not in line, line
