"""A cluster member recovers from the store failing under it (real PostgreSQL, in-process
members): a takeover whose load fails lets its leases go and is loaded on a later tick;
a reload of changed loops that fails is retried; a stored loop its owner has not loaded
yet answers 503 with Retry-After, not 404 (a takeover's load, a NOTIFY not taken yet)."""

from __future__ import annotations

import contextlib
import threading

import httpx
import psycopg
import pytest
import uvicorn

from service.daemon.api import create_app
from service.daemon.store_pg import CHANNEL
from service.engine.config import LoopConfig
from service.engine.modes import FROZEN
from service.wire.session import free_port
from tests.test_cluster_membership import LEASE_S, _member
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)


def test_a_takeover_whose_load_fails_is_loaded_on_a_later_tick(tmp_path, pg_url):
    configs = [LoopConfig(**loop_body(f"G{g}-{i}", gateway=f"gw{g}")) for g in range(4)
               for i in range(3)]  # fmt: skip
    a = _member(tmp_path, pg_url, "a")
    try:
        a.register_many(configs)
        b = _member(tmp_path / "b", pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
        try:
            adopt, failed = b.adopt_shards, []

            def fails_once(shards, token):
                if not failed:
                    failed.append(list(shards))
                    raise psycopg.OperationalError("the store went away mid-load")
                return adopt(shards, token)

            b.adopt_shards = fails_once
            # b wins some shards; its first load fails; a later tick takes them again
            # (a signal wait: about 2 s alone, far longer on a loaded CI box)
            wait_until(lambda: failed and b.loop_ids(), timeout=60.0, what="b loading")
            ids = {c.id for c in configs}
            wait_until(lambda: set(a.loop_ids()) | set(b.loop_ids()) == ids,
                       timeout=60.0, what="every loop owned and loaded")  # fmt: skip
            assert not set(a.loop_ids()) & set(b.loop_ids())
            assert {c.split("-")[0] for c in b.loop_ids()} >= {
                s.removeprefix("gw:").replace("gw", "G") for s in failed[0]
            }
        finally:
            b.stop()
    finally:
        a.stop()


def test_a_reload_that_fails_is_retried(tmp_path, pg_url):
    tuner = _member(tmp_path, pg_url, "a")
    load = tuner.store.load
    try:
        tuner.register_many([LoopConfig(**loop_body(f"L{i}")) for i in range(3)])
        failed = []

        def fails_once(ids=None, **kw):
            if ids == ["L1"] and not failed:  # the reload of the NOTIFY
                failed.append(ids)
                raise psycopg.OperationalError("server closed the connection unexpectedly")
            return load(ids=ids, **kw)

        tuner.store.load = fails_once
        with psycopg.connect(pg_url, autocommit=True) as conn:  # another member's patch
            conn.execute(
                'UPDATE loops SET config = (config::jsonb || \'{"mode": "frozen"}\')::text '
                "WHERE id = 'L1'"
            )
            conn.execute(f"NOTIFY {CHANNEL}, 'L1'")
        wait_until(lambda: failed, timeout=60.0, what="the failed reload")
        slot = tuner.table.slot("L1")
        wait_until(lambda: tuner.table.mode[slot] == FROZEN, timeout=60.0, what="the retry")
    finally:
        tuner.store.load = load
        tuner.stop()


@contextlib.contextmanager
def _served(tmp_path, pg_url: str, name: str, **extra):
    """A member with its API under uvicorn, at the URL it advertises to the cluster."""
    port = free_port()
    settings = tuner_settings(tmp_path / name, db_path=pg_url, instance_id=name,
                              cluster_lease_s=LEASE_S, api_port=port, **extra)  # fmt: skip
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, lifespan="on",
                                           log_config=None, access_log=False))  # fmt: skip
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_until(lambda: server.started, timeout=60.0, what=f"{name}'s API")
        yield app.state.tuner, f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30.0)


def test_a_stored_loop_its_owner_has_not_loaded_yet_is_a_503_not_a_404(tmp_path, pg_url):
    with _served(tmp_path, pg_url, "a") as (a, a_url):
        listen = a.settings.zenoh_listen
        with _served(tmp_path, pg_url, "b", zenoh_connect=listen) as (b, b_url):
            bodies = [loop_body(f"G{g}-0", gateway=f"gw{g}") for g in range(6)]
            assert httpx.post(f"{a_url}/loops/bulk", json=bodies).status_code == 201
            wait_until(lambda: a.loop_ids() and b.loop_ids(), timeout=60.0,
                       what="both members owning loops")  # fmt: skip
            b.reload_loops = lambda ids: None  # b is slow to take the NOTIFY of what follows
            gateway = b.table.gateways[b.table.slot(b.loop_ids()[0])]
            late = loop_body("LATE", gateway=gateway)  # stored through a, in b's shard
            assert httpx.post(f"{a_url}/loops/bulk", json=[late]).status_code == 201
            for url in (b_url, a_url):  # the owner, and a member forwarding to it
                r = httpx.get(f"{url}/loops/LATE")
                assert r.status_code == 503 and "owner is changing" in r.text, (url, r.text)
                assert r.headers["retry-after"]
