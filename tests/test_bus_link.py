"""Losing the bus is visible: ``pitune_bus_connected`` drops to 0, a WARNING says the link
went and an INFO that it is back, and ``/readyz`` says "disconnected" (not "starting") for
a tuner that had been connected. A real Zenoh router (a Python session in router mode)
that the tuner, a client, connects to; the real FastAPI app."""

from __future__ import annotations

import logging

import pytest
import zenoh
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from service.daemon.api import create_app
from service.wire.session import free_port, session_config
from tests.tuner_support import endpoint, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)


def _router(port: int) -> zenoh.Session:
    return zenoh.open(session_config(mode="router", listen=[endpoint(port)]))


def _gauge(client: TestClient) -> float:
    for family in text_string_to_metric_families(client.get("/metrics").text):
        if family.name == "pitune_bus_connected":
            return family.samples[0].value
    raise AssertionError("no pitune_bus_connected")


def _bus_lines(caplog, level: int) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "pitune.bus" and r.levelno == level]


def test_losing_the_router_is_counted_logged_and_reported(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="pitune.bus")
    port = free_port()
    settings = tuner_settings(
        tmp_path, zenoh_mode="client", zenoh_listen=[], zenoh_connect=[endpoint(port)]
    )
    router = _router(port)
    try:
        with TestClient(create_app(settings)) as client:
            wait_until(lambda: client.get("/readyz").status_code == 200, 30.0, "ready")
            assert _gauge(client) == 1.0
            assert _bus_lines(caplog, logging.WARNING) == []  # connecting is no loss

            router.close()
            wait_until(lambda: _gauge(client) == 0.0, 30.0, "the gauge at 0")
            ready = client.get("/readyz")
            assert ready.status_code == 503
            assert ready.json() == {
                "status": "disconnected",
                "detail": "bus not connected: no router or peer",
            }
            [lost] = _bus_lines(caplog, logging.WARNING)
            assert lost.startswith("bus disconnected: no router or peer reachable")
            assert client.get("/healthz").status_code == 200  # a restart does not fix it

            router = _router(port)
            wait_until(lambda: _gauge(client) == 1.0, 30.0, "the gauge back at 1")
            assert client.get("/readyz").status_code == 200
            [back] = _bus_lines(caplog, logging.INFO)
            assert back.startswith("bus connected again (routers [")
    finally:
        router.close()
    assert len(_bus_lines(caplog, logging.WARNING)) == 1  # closing the session is no loss


def test_a_tuner_never_connected_is_starting(tmp_path):
    settings = tuner_settings(tmp_path, zenoh_listen=[], zenoh_connect=[endpoint(free_port())])
    with TestClient(create_app(settings)) as client:
        ready = client.get("/readyz")
        assert (ready.status_code, ready.json()["status"]) == (503, "starting")
        assert _gauge(client) == 0.0


def test_a_listening_tuner_is_connected(tmp_path):
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        assert client.get("/readyz").status_code == 200
        assert _gauge(client) == 1.0
