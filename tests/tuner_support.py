"""Helpers shared by the tuner tests: ports, settings, Zenoh peers, waiting, snapshots.

``free_port`` is re-exported from :mod:`service.wire.session` for the tests that import it here.
"""

from __future__ import annotations

import json
import queue
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zenoh

from service.daemon.settings import Settings, load_settings
from service.wire.protocol import GainsMessage, Keys
from service.wire.session import free_port, session_config

TANK_SCALING = {"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0}


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def tuner_settings(tmp_path: Path, **overrides: object) -> Settings:
    """Settings for an in-process tuner: own port, own database, untrained agent."""
    values = {
        "zenoh_listen": [endpoint(free_port())],
        "db_path": tmp_path / "pitune.db",
        "agent_weights": "untrained",
        "instance_id": "test-tuner",
        "snapshot_interval_s": 3600.0,
        "max_sample_rate_hz": 1e6,
        # Starlette's TestClient names its host "testserver"; the gate's own tests use
        # the default (tests/test_api_gate.py)
        "api_allowed_hosts": ["127.0.0.1", "localhost", "::1", "testserver"],
    }
    return load_settings(**{**values, **overrides})


GATE_OFF = {"excitation_periods": 0.0}
"""Most tests feed a constant error: they test other things than the excitation gate."""


def loop_body(loop_id: str = "LIC-101", **overrides: object) -> dict:
    """A registration body for the paper's two-tank loop, 1 s samples, excitation gate
    off (``guard`` overrides are merged into that)."""
    guard = {**GATE_OFF, **overrides.pop("guard", {})}
    return {
        "id": loop_id,
        "kp": 0.5,
        "ki": 0.01,
        "sample_period_s": 1.0,
        "scaling": dict(TANK_SCALING),
        "guard": guard,
        **overrides,
    }


def open_peer(connect: list[str], *, admin: bool = False) -> zenoh.Session:
    """A loopback peer connected to ``connect``, multicast scouting off; ``admin``: with
    its own admin space, where :func:`subscribers` reads its view of the bus."""
    config = session_config(mode="peer", connect=connect)
    if admin:
        config.insert_json5("adminspace/enabled", "true")
    return zenoh.open(config)


def subscribers(session: zenoh.Session, key: str) -> set[str]:
    """Zenoh ids of the remote subscribers a put on ``key`` from ``session`` (opened with
    ``admin``) goes to, as that session knows them now: a declaration or undeclaration
    reaches it over each peer's own link, in no order with the other peers' ones."""
    zid = session.info.zid()
    ids: set[str] = set()
    for reply in session.get(f"@/{zid}/*/subscriber/{key}", timeout=5.0):
        if reply.ok is not None:
            for sources in json.loads(reply.ok.payload.to_bytes()).values():
                ids.update(sources)
    return ids


def wait_until(predicate: Callable[[], object], timeout: float = 5.0, what: str = "") -> object:
    """Poll ``predicate`` until truthy; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what or predicate}")
        time.sleep(0.01)


def snapshot_of(db: Path, loop_id: str) -> tuple[np.ndarray, dict] | None:
    """(hidden state, runtime) of the loop's last snapshot in a tuner's database, if any."""
    with sqlite3.connect(db) as conn:
        rows = conn.execute(
            "SELECT hidden, runtime FROM snapshots WHERE id = ?", (loop_id,)
        ).fetchall()
    if not rows:
        return None
    return np.frombuffer(rows[0][0], np.float32), json.loads(rows[0][1])


class Gateway:
    """A test gateway: publishes samples, collects gains messages (no blocking callback)."""

    def __init__(self, session: zenoh.Session, keys: Keys | None = None) -> None:
        self.session = session
        self.keys = keys or Keys()
        self.gains: queue.SimpleQueue[GainsMessage] = queue.SimpleQueue()
        self._sub = session.declare_subscriber(
            self.keys.all_gains,
            lambda s: self.gains.put(GainsMessage.model_validate_json(s.payload.to_bytes())),
        )

    def send(self, loop_id: str, payload: dict | bytes) -> None:
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        self.session.put(self.keys.sample(loop_id), data)

    def next_gains(self, timeout: float = 5.0) -> GainsMessage:
        return self.gains.get(timeout=timeout)

    def state(self, loop_id: str) -> tuple[bool, dict]:
        """(ok, reply) of the state queryable."""
        replies = list(self.session.get(self.keys.state(loop_id), timeout=5.0))
        assert len(replies) == 1, replies
        r = replies[0]
        return (
            (True, json.loads(r.ok.payload.to_bytes()))
            if r.ok
            else (
                False,
                json.loads(r.err.payload.to_bytes()),
            )
        )

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def connected_gateway(settings: Settings) -> Gateway:
    """A gateway peer connected to the tuner, once the tuner's subscriptions reach it."""
    gw = Gateway(open_peer(settings.zenoh_listen), settings.keys)
    wait_until(
        lambda: list(gw.session.liveliness().get(settings.keys.all_tuners, timeout=1.0)),
        what="tuner liveliness token",
    )
    return gw
