"""The shipped Zenoh ACL with the services' real ways of talking, on loopback.

Issue 19: in the compose stack the tuner received 0 samples through the router while
tests/test_deploy.py passed. Those tests put with ``Session.put``; the plant simulator
(and any Zenoh-idiomatic DCS gateway) puts through a *declared publisher*, and a declared
publisher of Zenoh 1.x only sends when it knows of a matching subscriber: it learns of
them from the router, which forwards subscriber declarations to it (the ``egress``
``declare_subscriber`` of the ACL). The ACL denied that forwarding (default deny), so the
plant's publisher dropped every sample on its own side, silently. Queriers
(``declare_querier``) work the same way with queryable declarations.

These tests use what the deployment uses: the router is ``deploy/zenoh_router.py`` (the
zenohd stand-in) loaded from ``deploy/zenoh/router.json5`` with the example credentials,
the clients load ``tuner.json5`` and ``gateway.json5``; the last test runs the ``pitune
tuner`` and ``pitune plant run`` commands with the compose file's settings.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import zenoh

from service.wire.protocol import Keys
from service.wire.session import free_port, session_config
from tests.tuner_support import wait_until

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
ZENOH = DEPLOY / "zenoh"
KEYS = Keys()


@contextmanager
def python_router(
    tmp_path: Path,
    config: Path = ZENOH / "router.json5",
    credentials: Path = ZENOH / "credentials.txt",
) -> Iterator[str]:
    """deploy/zenoh_router.py from ``config`` on a free loopback port (the example
    credentials by default); yields the endpoint clients connect to."""
    port = free_port()
    log = tmp_path / "router.log"
    credentials = json.dumps(str(credentials))
    argv = [sys.executable, str(DEPLOY / "zenoh_router.py"), "--config", str(config),
            "--set", f'listen/endpoints=["tcp/127.0.0.1:{port}"]',
            "--set", f"transport/auth/usrpwd/dictionary_file={credentials}"]  # fmt: skip
    with log.open("w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while "listening" not in log.read_text():
            assert proc.poll() is None, f"the router exited: {log.read_text()}"
            assert time.monotonic() < deadline, f"the router did not start: {log.read_text()}"
            time.sleep(0.1)
        assert "access control on" in log.read_text(), log.read_text()
        yield f"tcp/127.0.0.1:{port}"
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def client(user: str, endpoint: str) -> zenoh.Session:
    """A session as the services build theirs: the user's deploy config through
    :func:`service.wire.session.session_config`, connected to ``endpoint``."""
    return zenoh.open(session_config(config_file=ZENOH / f"{user}.json5", connect=[endpoint]))


@pytest.fixture
def router(tmp_path) -> Iterator[str]:
    with python_router(tmp_path) as endpoint:
        yield endpoint


def first_through(put, q: queue.SimpleQueue, timeout: float = 10.0) -> None:
    """``put()`` every 50 ms until something arrives on ``q`` (the routes through the
    router are up: declarations and interests propagated), then empty ``q``. A put made
    before the subscriber's declaration reached the router is dropped, as Zenoh does."""
    deadline = time.monotonic() + timeout
    while True:
        put()
        try:
            q.get(timeout=0.05)
            break
        except queue.Empty:
            assert time.monotonic() < deadline, "nothing got through the router"
    while received(q, 1, timeout=0.2):  # the probes still on their way
        pass


def received(q: queue.SimpleQueue, n: int, timeout: float = 5.0) -> list[str]:
    out, deadline = [], time.monotonic() + timeout
    while len(out) < n and (left := deadline - time.monotonic()) > 0:
        try:
            out.append(q.get(timeout=left))
        except queue.Empty:
            break
    return out


def received_until(q: queue.SimpleQueue, last, timeout: float = 5.0) -> list:
    """What ``q`` receives up to and including ``last`` (all of it on a timeout)."""
    out, deadline = [], time.monotonic() + timeout
    while (not out or out[-1] != last) and (left := deadline - time.monotonic()) > 0:
        try:
            out.append(q.get(timeout=left))
        except queue.Empty:
            break
    return out


# (publishing user, key it publishes, subscribing user, key expression it subscribes)
FLOWS = {
    "sample": ("gateway", KEYS.sample("tank1"), "tuner", KEYS.all_samples),
    "sample batch": ("gateway", KEYS.batch, "tuner", KEYS.batch),
    "gateway's batch": (
        "gateway",
        KEYS.gateway_samples("gw-1"),
        "tuner",
        KEYS.gateway_samples("gw-1"),
    ),
    "gains": ("tuner", KEYS.gains("tank1"), "gateway", KEYS.all_gains),
    "gains batch": ("tuner", KEYS.gateway_gains("gw-1"), "gateway", KEYS.gateway_gains("gw-1")),
}


@pytest.mark.parametrize("declared", [True, False], ids=["declared publisher", "session.put"])
@pytest.mark.parametrize("flow", FLOWS)
def test_every_protocol_flow_passes_the_shipped_acl(router, flow, declared):
    """Each put of docs/protocol.md reaches its subscriber through the shipped ACL, from a
    declared publisher (what the plant simulator uses) as well as from ``Session.put``,
    whichever of the two sessions came first."""
    pub_user, key, sub_user, sub_key = FLOWS[flow]
    got: queue.SimpleQueue = queue.SimpleQueue()
    publisher_session = client(pub_user, router)
    subscriber_session = client(sub_user, router)
    entities = []
    try:
        if declared:
            entities.append(publisher_session.declare_publisher(key))
        entities.append(subscriber_session.declare_subscriber(sub_key, lambda s: got.put(1)))

        def put() -> None:
            if declared:
                entities[0].put(b"{}")
            else:
                publisher_session.put(key, b"{}")

        first_through(put, got)
        for _ in range(5):
            put()
        n = len(received(got, 5))
        assert n == 5, f"{flow}: {n} of 5 puts reached the {sub_user} through the ACL"
    finally:
        for entity in entities:
            entity.undeclare()
        subscriber_session.close()
        publisher_session.close()


# (the tuner's queryable, the key a gateway asks): per loop, and StateBatch per gateway
QUERIES = {
    "loop state": (KEYS.all_states, KEYS.state("t1")),
    "gateway state": (KEYS.all_gateway_states, KEYS.gateway_state("gw-1")),
}


@pytest.mark.parametrize("declared", [True, False], ids=["declared querier", "session.get"])
@pytest.mark.parametrize("query", QUERIES)
def test_state_queries_reach_the_tuners_queryable_through_the_shipped_acl(router, query, declared):
    """A gateway asking the state (a loop's, or its StateBatch) gets the tuner's reply,
    with ``Session.get`` as well as with a declared querier."""
    served, asked = QUERIES[query]
    tuner, gateway = client("tuner", router), client("gateway", router)
    entities = []
    try:
        entities.append(tuner.declare_queryable(served, lambda q: q.reply(q.key_expr, b"{}")))
        if declared:
            entities.append(gateway.declare_querier(asked, timeout=3.0))

        def answered() -> int:  # the queryable's declaration may still be on its way
            replies = entities[1].get() if declared else gateway.get(asked, timeout=3.0)
            return len([r for r in replies if r.ok is not None])

        deadline = time.monotonic() + 10.0
        while not (n := answered()) and time.monotonic() < deadline:
            pass
        assert n == 1, f"{query}: {n} replies"
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        gateway.close()
        tuner.close()


def test_the_acl_still_denies_a_gateway_the_samples_and_a_tuner_the_gains(router):
    """Seeing a subscriber's declaration is not receiving its data: the gateway user still
    cannot hear samples, nor publish gains; the tuner user still cannot publish samples."""
    got: queue.SimpleQueue = queue.SimpleQueue()
    users = ("tuner", "tuner", "gateway", "gateway")
    tuner, rogue_tuner, gateway, rogue = (client(u, router) for u in users)
    entities = []

    def heard(what: str):
        return lambda s: got.put((what, s.payload.to_bytes()))

    try:
        entities = [
            rogue.declare_subscriber(KEYS.all_samples, heard("rogue heard a sample")),
            tuner.declare_subscriber(KEYS.all_samples, heard("tuner got a sample")),
            gateway.declare_subscriber(KEYS.all_gains, heard("gateway got gains")),
        ]
        forged_gains = rogue.declare_publisher(KEYS.gains("tank1"))
        forged_sample = rogue_tuner.declare_publisher(KEYS.sample("tank1"))
        entities += [forged_gains, forged_sample]
        # real traffic flows both ways first (so a forged put could not be lost for lack
        # of a route), then each forged put is followed by a control put of the same
        # session: the router takes a session's messages in order, so once both controls
        # arrived, both forged puts were handled
        first_through(lambda: gateway.put(KEYS.sample("tank1"), b"probe"), got)
        first_through(lambda: tuner.put(KEYS.gains("tank1"), b"probe"), got)
        forged_gains.put(b"forged")
        rogue.put(KEYS.sample("tank1"), b"control")  # gateway user: samples are allowed
        forged_sample.put(b"forged")
        rogue_tuner.put(KEYS.gains("tank1"), b"control")  # tuner user: gains allowed
        seen = set(received(got, 3, timeout=5.0))
        seen |= set(received(got, 5, timeout=0.2))  # anything else still on its way
        assert seen == {
            ("tuner got a sample", b"control"),
            ("gateway got gains", b"control"),
            ("rogue heard a sample", b"control"),  # its own put, delivered locally
        }
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        for session in (rogue, gateway, rogue_tuner, tuner):
            session.close()


def pitune(*args: str) -> list[str]:
    return [sys.executable, "-m", "service.cli", *args]


def compose_tuner(endpoint: str, api_port: int, db: Path) -> dict[str, str]:
    """The compose file's PITUNE_* settings of ``pitune tuner``: the router's client as
    the tuner user (tuner.json5), here on ``endpoint`` with its API on ``api_port``."""
    return {
        "PITUNE_ZENOH_MODE": "client",
        "PITUNE_ZENOH_CONFIG": str(ZENOH / "tuner.json5"),
        "PITUNE_ZENOH_CONNECT": json.dumps([endpoint]),
        "PITUNE_ZENOH_LISTEN": "[]",
        "PITUNE_API_HOST": "127.0.0.1",
        "PITUNE_API_PORT": str(api_port),
        "PITUNE_DB_PATH": str(db),
        "PITUNE_LOG_LEVEL": "warning",
    }


def test_tuner_and_plant_commands_tune_through_the_router_with_the_shipped_acl(tmp_path):
    """The compose stack without containers: ``pitune tuner`` with the compose file's
    PITUNE_* settings and tuner.json5, ``pitune plant run`` with gateway.json5 (declared
    publishers), both clients of the router loaded from router.json5. The tuner receives
    the plant's samples and the plant applies the tuner's gains."""
    api_port = free_port()
    api = f"http://127.0.0.1:{api_port}"
    token = "acl-live-test"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PITUNE_")}
    env.update(PYTHONPATH=str(ROOT), PITUNE_API_TOKEN=token)
    with python_router(tmp_path) as endpoint:
        tuner_env = {**env, **compose_tuner(endpoint, api_port, tmp_path / "pitune.db")}
        plant_argv = pitune("plant", "run", "--tank", "tank1", "--speed", "60", "--noise", "1",
                            "--sp-period", "120", "--register", api,
                            "--zenoh-config", str(ZENOH / "gateway.json5"),
                            "--connect", endpoint, "--progress", "0")  # fmt: skip
        logs = {name: (tmp_path / f"{name}.log").open("w") for name in ("tuner", "plant")}
        procs = {}
        try:
            procs["tuner"] = subprocess.Popen(
                pitune("tuner"), env=tuner_env, stdout=logs["tuner"], stderr=subprocess.STDOUT
            )
            procs["plant"] = subprocess.Popen(
                plant_argv, env=env, stdout=logs["plant"], stderr=subprocess.STDOUT
            )
            view, deadline = {}, time.monotonic() + 90
            while time.monotonic() < deadline:
                for name, proc in procs.items():
                    assert proc.poll() is None, (tmp_path / f"{name}.log").read_text()[-3000:]
                try:
                    view = httpx.get(f"{api}/loops/tank1", timeout=5).json()
                except (httpx.HTTPError, ValueError):
                    view = {}
                if view.get("seq", 0) >= 2:
                    break
                time.sleep(1.0)
            samples = view.get("counters", {}).get("samples", 0)
            assert samples > 0, f"the tuner received no sample through the router: {view}"
            assert view.get("seq", 0) >= 2, f"no gains published within 90 s: {view}"
        finally:
            for name in ("plant", "tuner"):
                if name in procs:
                    procs[name].terminate()
            for name in ("plant", "tuner"):
                if name in procs:
                    try:
                        procs[name].wait(20)
                    except subprocess.TimeoutExpired:
                        procs[name].kill()
                        procs[name].wait()
            for f in logs.values():
                f.close()
        plant_log = (tmp_path / "plant.log").read_text()
        applied = [line for line in plant_log.splitlines() if "gain updates applied" in line]
        assert applied and not applied[-1].startswith("plant stopped: 0 gain"), plant_log[-2000:]


def test_tuners_watch_each_others_tokens_through_the_shipped_acl(router):
    """The tuner user may watch and query pitune/tuners/*: what a tuner's start-up check
    (one tuner per key prefix), its watch for a tuner that comes later, and a cluster
    member's crash detection (a member's token gone at once) are made of. The other
    tuner's token comes, a query finds it, and it goes with its session; a gateway user's
    token there never reaches them (before the fix the tuner user saw nothing at all)."""
    events: queue.SimpleQueue = queue.SimpleQueue()
    samples: queue.SimpleQueue = queue.SimpleQueue()
    users = ("tuner", "tuner", "gateway")
    member, other, gateway = (client(u, router) for u in users)
    entities = []

    def tokens() -> list[str]:
        replies = member.liveliness().get(KEYS.all_tuners, timeout=5.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    try:
        entities = [
            member.liveliness().declare_subscriber(
                KEYS.all_tuners, lambda s: events.put((str(s.key_expr), s.kind)), history=True
            ),
            member.declare_subscriber(KEYS.all_samples, lambda s: samples.put(1)),
            gateway.liveliness().declare_token(KEYS.tuner("impostor")),
        ]
        # the gateway's puts reach the member after the router handled its token
        first_through(lambda: gateway.put(KEYS.sample("tank1"), b"{}"), samples)
        _token = other.liveliness().declare_token(KEYS.tuner("other"))  # dropped: undeclared
        put, gone = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE
        assert received(events, 1, timeout=10.0) == [(KEYS.tuner("other"), put)]
        # (a query right after the token's event came back empty now and then: asked again)
        wait_until(lambda: tokens() == [KEYS.tuner("other")], what="a query finding it")
        other.close()  # as a crash does: its connection closes, its token goes at once
        # (a subscriber with history may get the token's PUT twice, from its history query
        # and live: CI saw the repeat come before the DELETE)
        after = received_until(events, (KEYS.tuner("other"), gone), timeout=10.0)
        assert after[-1:] == [(KEYS.tuner("other"), gone)], after
        assert all(event == (KEYS.tuner("other"), put) for event in after[:-1]), after
        assert tokens() == []
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        for session in (gateway, other, member):
            session.close()


def test_a_second_tuner_on_the_prefix_refuses_to_start_through_the_router(tmp_path, caplog):
    """Two tuners with one key prefix, both clients of the router loaded from router.json5
    as the compose file runs them: the second finds the first's token, waits out a lease
    and exits with EXIT_LOCKED; the first sees the second's token come and go. Before the
    fix the ACL gave the tuner user no liveliness subscriber or query: both ran, /healthz
    ok, tuning the same loops."""
    from service.daemon.main import EXIT_LOCKED
    from service.daemon.tuner import Tuner
    from tests.tuner_support import tuner_settings

    with python_router(tmp_path) as endpoint:
        settings = tuner_settings(tmp_path, zenoh_config=ZENOH / "tuner.json5",
                                  zenoh_mode="client", zenoh_connect=[endpoint],
                                  zenoh_listen=[], instance_id="first")  # fmt: skip
        first = Tuner(settings).start()
        try:
            env = {k: v for k, v in os.environ.items() if not k.startswith("PITUNE_")}
            env.update(compose_tuner(endpoint, free_port(), tmp_path / "second.db"))
            env.update(PYTHONPATH=str(ROOT), PITUNE_API_TOKEN="x" * 32,
                       PITUNE_INSTANCE_ID="second", PITUNE_AGENT_WEIGHTS="untrained")  # fmt: skip
            try:  # it exits after PREFIX_LEASE_S (12 s) plus its start-up
                second = subprocess.run(
                    pitune("tuner"), env=env, capture_output=True, text=True, timeout=90
                )
            except subprocess.TimeoutExpired as exc:  # killed by run()
                raise AssertionError(f"it ran beside the first: {exc.stderr}") from None
            refusal = [line for line in second.stderr.splitlines() if "cannot start" in line]
            assert second.returncode == EXIT_LOCKED, second.stderr[-3000:]
            assert "another tuner runs on the bus with key prefix 'pitune' " \
                "(pitune/tuners/first)" in refusal[-1]  # fmt: skip
            wait_until(lambda: "the other tuner pitune/tuners/second left" in caplog.text,
                       timeout=15.0, what="the second tuner's token gone")  # fmt: skip
            assert "another tuner appeared on the bus with key prefix 'pitune': " \
                "pitune/tuners/second" in caplog.text  # fmt: skip
        finally:
            first.stop()
