"""Issue 18 defect 10: ready means samples can arrive and gains can leave. A tuner that
connects to a router or peer is ready only while one is connected (``Tuner.bus_ready``,
what ``/readyz`` reports); a tuner that only listens is ready once its session is open."""

from __future__ import annotations

import pytest
import zenoh

from service.daemon.tuner import Tuner
from service.wire.session import free_port, session_config
from tests.tuner_support import endpoint, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)


def _router(port: int) -> zenoh.Session:
    return zenoh.open(session_config(mode="router", listen=[endpoint(port)]))


def test_a_tuner_cut_off_from_its_router_is_not_ready(tmp_path):
    port = free_port()
    settings = tuner_settings(tmp_path, zenoh_listen=[], zenoh_connect=[endpoint(port)])
    with Tuner(settings) as tuner:
        assert tuner.alive and not tuner.bus_ready and not tuner.ready  # no router yet
        router = _router(port)
        try:
            wait_until(lambda: tuner.ready, timeout=30.0, what="the tuner connected")
        finally:
            router.close()
        wait_until(lambda: not tuner.ready, timeout=30.0, what="the router gone")
        assert tuner.alive and tuner.bus.is_open  # what /readyz used to check
        router = _router(port)
        try:
            wait_until(lambda: tuner.ready, timeout=30.0, what="the router back")
        finally:
            router.close()


def test_a_listening_tuner_is_ready_once_open(tmp_path):
    with Tuner(tuner_settings(tmp_path)) as tuner:
        assert tuner.ready
    assert not tuner.ready
