"""``pitune tuner`` as a real subprocess: SIGKILL loses nothing, SIGTERM shuts down cleanly."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.tuner_support import (
    Gateway,
    endpoint,
    free_port,
    loop_body,
    open_peer,
    wait_until,
)

pytestmark = pytest.mark.timeout(120)
ROOT = Path(__file__).resolve().parents[1]
TOKEN = "daemon-token"


class Daemon:
    """One ``python -m service.cli tuner`` process; always reaped."""

    def __init__(self, tmp_path: Path, *args: str, env: dict | None = None) -> None:
        self.api = f"http://127.0.0.1:{free_port()}"
        self.zenoh = endpoint(free_port())
        self.db = tmp_path / "state" / "pitune.db"
        self.log = tmp_path / "daemon.log"
        self.args = [
            "--api-port", self.api.rsplit(":", 1)[1], "--listen", self.zenoh, "--db", str(self.db),
            "--agent-weights", "untrained", "--instance-id", "proc", *args,
        ]  # fmt: skip
        self.env = {**os.environ, "PYTHONPATH": str(ROOT), "PITUNE_API_TOKEN": TOKEN, **(env or {})}
        self.proc: subprocess.Popen | None = None

    def start(self) -> "Daemon":
        with self.log.open("a") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "service.cli", "tuner", *self.args],
                cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT,
            )  # fmt: skip
        wait_until(self._ready, timeout=60.0, what=f"daemon ready (log: {self.log})")
        return self

    def _ready(self) -> bool:
        assert self.proc.poll() is None, self.log.read_text()
        try:
            return httpx.get(f"{self.api}/readyz", timeout=1.0).status_code == 200
        except httpx.TransportError:
            return False

    def signal(self, sig: int, timeout: float = 30.0) -> int:
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=timeout)

    def reap(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def http(self) -> httpx.Client:
        return httpx.Client(base_url=self.api, headers={"Authorization": f"Bearer {TOKEN}"})


@pytest.fixture
def daemon(tmp_path):
    d = Daemon(tmp_path, "--snapshot-interval", "0.2", env={"PITUNE_MAX_SAMPLE_RATE_HZ": "1e6"})
    try:
        yield d
    finally:
        d.reap()


def db_rows(db: Path, sql: str) -> list:
    with sqlite3.connect(db) as conn:
        return conn.execute(sql).fetchall()


def snapshot_of(db: Path, loop_id: str) -> tuple[np.ndarray, dict] | None:
    rows = db_rows(db, f"SELECT hidden, runtime FROM snapshots WHERE id = '{loop_id}'")
    if not rows:
        return None
    return np.frombuffer(rows[0][0], np.float32), json.loads(rows[0][1])


def test_sigkill_loses_no_loop_and_no_audit_entry_and_tuning_resumes(daemon):
    daemon.start()
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
        assert daemon.signal(signal.SIGKILL) == -signal.SIGKILL
    finally:
        gw.close()

    hidden, runtime = snapshot_of(daemon.db, "LIC-101")
    assert np.linalg.norm(hidden) > 0
    daemon.start()
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
    assert daemon.signal(signal.SIGTERM) == 0


def test_sigterm_snapshots_closes_the_session_and_exits_zero(tmp_path):
    d = Daemon(tmp_path, "--snapshot-interval", "3600", "--prefix", "site1/pitune")
    try:
        d.start()
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
            assert d.signal(signal.SIGTERM) == 0
            assert not list(gw.session.liveliness().get(alive, timeout=1.0))
        finally:
            gw.close()
        hidden, runtime = snapshot_of(d.db, "FIC-7")
        assert runtime["last_t"] == 9.0 and runtime["counters"][0] == 10
        assert "tuner proc stopped" in d.log.read_text()
    finally:
        d.reap()


def test_invalid_settings_exit_with_status_2(tmp_path):
    argv = ["tuner", "--prefix", "a//b", "--db", str(tmp_path / "x")]
    proc = subprocess.run(
        [sys.executable, "-m", "service.cli", *argv],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "invalid settings" in proc.stderr and "key prefix" in proc.stderr


def test_a_store_that_keeps_failing_makes_the_daemon_exit_for_a_restart(tmp_path):
    """A database locked by another process: no gains go out, and after
    store_failure_exit_s the daemon exits (74) and restarts from what was published."""
    env = {"PITUNE_MAX_SAMPLE_RATE_HZ": "1e6", "PITUNE_STORE_FAILURE_EXIT_S": "1"}
    d = Daemon(tmp_path, env=env)
    try:
        d.start()
        with d.http() as api:
            assert api.post("/loops", json=loop_body("LIC-101")).status_code == 201
        gw = Gateway(open_peer([d.zenoh]))
        locker = sqlite3.connect(d.db, isolation_level=None)
        try:
            wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
            locker.execute("BEGIN IMMEDIATE")  # holds the write lock
            for i in range(170):
                gw.send("LIC-101", {"t": float(i), "e": 1.0})
            assert d.proc.wait(timeout=60) == 74  # two 5 s busy timeouts, 1 s apart
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
        d.reap()
