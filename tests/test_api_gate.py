"""What every HTTP request passes before a route reads it (service.daemon.gate): the Host,
a browser's Origin, the token of a REST change, the body's size. The real app under
uvicorn over HTTP (a raw socket where the body must not be sent)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading

import httpx
import pytest
import uvicorn

from plant_sim.config import LoopSpec
from plant_sim.registration import register
from service.daemon.api import create_app
from service.daemon.gate import (
    BODY_BYTES,
    FAILURE_WINDOW_S,
    LOGIN_BODY_BYTES,
    MAX_FAILURES,
    allowed_hosts,
)
from service.daemon.settings import load_settings
from service.daemon.store_pg import redacted
from service.gateways.opcua.register import register_loops
from service.gateways.opcua.sitemap import parse_map
from service.gateways.registration import RegistrationError
from service.wire.session import free_port
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
TOKEN = "gate-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@contextlib.contextmanager
def _served(tmp_path, **settings):
    """The app under uvicorn on loopback (by default with the default allowed hosts),
    believing proxy headers from ``api_trusted_proxies`` only, as ``pitune tuner`` does."""
    port = free_port()
    settings = tuner_settings(tmp_path, **{"api_port": port, "api_allowed_hosts": None, **settings})
    app = create_app(settings)
    config = uvicorn.Config(
        app, host="127.0.0.1", port=port, lifespan="on", log_config=None, access_log=False,
        forwarded_allow_ips=settings.api_trusted_proxies,
    )  # fmt: skip
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_until(lambda: server.started, timeout=60.0, what="the API")
        yield app.state.tuner, port
    finally:
        server.should_exit = True
        thread.join(timeout=30.0)


def _answer_to_headers_only(port: int, head: str) -> str:
    """Send a request's head (announcing a body) and no body; the status line of the
    answer, which must come without the body (a 20 s wait for it fails the test)."""
    with socket.create_connection(("127.0.0.1", port), timeout=20.0) as sock:
        sock.sendall(head.encode() + b"\r\n")
        return sock.recv(4096).decode().split("\r\n", 1)[0]


def test_an_unauthenticated_change_is_refused_before_its_body_is_read(tmp_path):
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        host = f"Host: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
        head = f"POST /loops/bulk HTTP/1.1\r\n{host}Content-Length: {BODY_BYTES - 1}\r\n"
        assert _answer_to_headers_only(port, head) == "HTTP/1.1 401 Unauthorized"
        # a length over every route's limit is refused by its length alone, token or not
        for auth in ("", f"Authorization: Bearer {TOKEN}\r\n"):
            head = f"POST /loops HTTP/1.1\r\n{host}{auth}Content-Length: 24000000\r\n"
            assert _answer_to_headers_only(port, head) == "HTTP/1.1 413 Request Entity Too Large"
        assert tuner.loop_ids() == []
        # the bulk route's own limit is the larger: 2 MiB of it is taken, with the token
        body = httpx.Request("POST", "http://x", json=[loop_body("B1"), loop_body("B2")]).content
        padded = body[:-1] + b" " * (2 << 20) + b"]"
        r = httpx.post(f"http://127.0.0.1:{port}/loops/bulk", content=padded,
                       headers={**AUTH, "Content-Type": "application/json"})  # fmt: skip
        assert r.status_code == 201, r.text
        assert sorted(tuner.loop_ids()) == ["B1", "B2"]


def test_a_body_that_streams_past_its_limit_is_refused_and_changes_nothing(tmp_path):
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        big = loop_body("L1")  # a valid registration, padded past 1 MiB below
        padding = b" " * (BODY_BYTES + 10)
        body = httpx.Request("POST", "http://x", json=big).content[:-1] + padding + b"}"

        def chunks():  # no Content-Length: chunked transfer
            for i in range(0, len(body), 65536):
                yield body[i : i + 65536]

        r = httpx.post(f"http://127.0.0.1:{port}/loops", content=chunks(),
                       headers={**AUTH, "Content-Type": "application/json"})  # fmt: skip
        assert r.status_code == 413, r.text
        assert tuner.loop_ids() == []
        # the same registration at its own size is taken
        r = httpx.post(f"http://127.0.0.1:{port}/loops", json=big, headers=AUTH)
        assert r.status_code == 201, r.text
        # the login form has its own, small limit
        r = httpx.post(f"http://127.0.0.1:{port}/ui/login",
                       content=b"token=" + b"a" * LOGIN_BODY_BYTES,
                       headers={"Content-Type": "application/x-www-form-urlencoded"})  # fmt: skip
        assert r.status_code == 413


def test_a_loopback_api_answers_only_to_loopback_host_names(tmp_path):
    with _served(tmp_path) as (tuner, port):  # no token: open on loopback
        url = f"http://127.0.0.1:{port}"
        httpx.post(f"{url}/loops", json=loop_body("L1")).raise_for_status()
        # DNS rebinding: a page of evil.example resolved to 127.0.0.1 sends its own Host
        rebound = {"Host": f"evil.example:{port}"}
        assert httpx.get(f"{url}/loops/L1", headers=rebound).status_code == 400
        assert httpx.post(f"{url}/loops/L1/reset", headers=rebound).status_code == 400
        assert httpx.get(f"{url}/loops/L1", headers={"Host": f"localhost:{port}"}).is_success
        assert tuner.views(0, 10).items[0].seq == 0  # nothing was reset


def test_a_browsers_cross_site_change_is_refused(tmp_path):
    with _served(tmp_path) as (tuner, port):  # no token: open on loopback
        url = f"http://127.0.0.1:{port}"
        httpx.post(f"{url}/loops", json=loop_body("L1")).raise_for_status()
        for origin in ("http://evil.example", "null"):
            r = httpx.post(f"{url}/loops/L1/reset", headers={"Origin": origin})
            assert r.status_code == 403, (origin, r.text)
        assert tuner.views(0, 10).items[0].seq == 0
        # a page of the API's own origin (the console), and a script without Origin
        assert httpx.post(f"{url}/loops/L1/reset", headers={"Origin": url}).is_success
        assert httpx.post(f"{url}/loops/L1/reset").is_success
        assert tuner.views(0, 10).items[0].seq == 2


def test_the_allowed_hosts_default_to_loopback_names_only_on_loopback():
    assert allowed_hosts(load_settings(api_host="127.0.0.1")) == {"127.0.0.1", "localhost", "::1"}
    assert allowed_hosts(load_settings(api_host="0.0.0.0")) is None  # behind a proxy or NAT
    chosen = load_settings(api_host="0.0.0.0", api_allowed_hosts=["Tuner.Plant.Local"])
    assert allowed_hosts(chosen) == {"tuner.plant.local"}


def test_a_postgresql_password_is_shown_to_no_one(tmp_path, pg_url):
    """The console's tuner view (read without a login) and /healthz show the store's
    location with its password redacted, in the user part or a query parameter."""
    secret = "Pg-S3cret-Pw"
    sep = "&" if "?" in pg_url else "?"
    with _served(tmp_path, db_path=f"{pg_url}{sep}password={secret}") as (tuner, port):
        for path in ("/ui/api/tuner", "/healthz"):
            r = httpx.get(f"http://127.0.0.1:{port}{path}")
            assert r.is_success and secret not in r.text, (path, r.text[:300])
        assert "password=***" in httpx.get(f"http://127.0.0.1:{port}/ui/api/tuner").text
    url = f"postgresql://pitune:{secret}@db:5432/pitune?sslmode=require&password={secret}"
    assert redacted(url) == url.replace(secret, "***")


def test_a_client_guessing_tokens_is_locked_out_and_logged(tmp_path, caplog):
    """MAX_FAILURES wrong tokens (REST and console login together) lock the client out,
    the right token too, until they age; the lock-out is a WARNING."""
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        for k in range(MAX_FAILURES - 1):
            r = httpx.post(f"{url}/loops/L{k}/reset", headers={"Authorization": f"Bearer {k}"})
            assert r.status_code == 401
        r = httpx.post(f"{url}/ui/login", data={"token": "guess"})  # the tenth, at the console
        assert r.status_code == 303 and "error=wrong_token" in r.headers["location"]
        for attempt in ({"headers": AUTH, "json": loop_body("L1")}, {"headers": {}}):
            r = httpx.post(f"{url}/loops", **attempt)
            assert r.status_code == 429, r.text
            assert 0 < int(r.headers["Retry-After"]) <= FAILURE_WINDOW_S
        r = httpx.post(f"{url}/ui/login", data={"token": TOKEN})
        assert r.status_code == 429
        assert tuner.loop_ids() == []
        assert httpx.get(f"{url}/loops").is_success  # reads stay open
    locked = [r for r in caplog.records if "locked out" in r.getMessage()]
    assert len(locked) == 1 and locked[0].levelname == "WARNING"


def test_a_gateways_token_registers_its_own_loops_and_nothing_else(tmp_path):
    gw_token = "gateway-one-token-0123456789"
    mine = {"Authorization": f"Bearer {gw_token}"}
    with _served(tmp_path, api_token=TOKEN, api_gateway_tokens={"gw-1": gw_token}) as (
        tuner, port,
    ):  # fmt: skip
        url = f"http://127.0.0.1:{port}"
        r = httpx.post(f"{url}/loops", json=loop_body("A", gateway="gw-1"), headers=mine)
        assert r.status_code == 201, r.text
        pair = [loop_body("B", gateway="gw-1"), loop_body("C", gateway="gw-1")]
        r = httpx.post(f"{url}/loops/bulk", headers=mine, json=pair)
        assert r.status_code == 201, r.text
        for body in (loop_body("X", gateway="gw-2"), loop_body("X")):  # another's, or none
            r = httpx.post(f"{url}/loops", json=body, headers=mine)
            assert r.status_code == 403, r.text
        mixed = [loop_body("Y", gateway="gw-1"), loop_body("Z", gateway="gw-2")]
        r = httpx.post(f"{url}/loops/bulk", headers=mine, json=mixed)
        assert r.status_code == 403 and "'Z'" in r.text
        httpx.post(f"{url}/loops", json=loop_body("O"), headers=AUTH).raise_for_status()
        for method, path, body in (
            ("PATCH", "/loops/O", {"kp_max": 1e6}),
            ("PATCH", "/loops/A", {"kp_max": 1e6}),  # its own loop: registration only
            ("DELETE", "/loops/O", None),
            ("POST", "/loops/A/reset", None),
        ):
            r = httpx.request(method, f"{url}{path}", json=body, headers=mine)
            assert r.status_code == 403, (method, path, r.text)
        assert sorted(tuner.loop_ids()) == ["A", "B", "C", "O"]
        assert tuner.view("O").config.guard.kp_max < 1e6


def _actors(url: str, loop_id: str) -> dict[str, str]:
    """Reason -> the actor of the loop's audit rows (JSON detail, or 'actor=' text)."""
    items = httpx.get(f"{url}/loops/{loop_id}/history").json()["items"]
    out = {}
    for row in items:
        detail = row["detail"] or ""
        try:
            out[row["reason"]] = json.loads(detail)["actor"]
        except (ValueError, KeyError, TypeError):
            out[row["reason"]] = detail.rpartition("actor=")[2] if "actor=" in detail else ""
    return out


def test_a_short_gateway_token_is_warned_about_at_start_up(tmp_path, caplog):
    """As a short admin token is (it took 1 character without a word), and an open API
    with gateway tokens, which restrict nothing there; no token in the log."""
    short = "gw-tok-1234"
    with _served(tmp_path, api_token=TOKEN, api_gateway_tokens={"gw-1": short}):
        pass
    with _served(tmp_path / "open", api_gateway_tokens={"gw-2": GW_A}):
        pass
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "the API token of gateway 'gw-1' has 11 characters: guessable" in "\n".join(warnings)
    assert any("gateway tokens are set but no admin token" in w for w in warnings)
    assert not [w for w in warnings if short in w or GW_A in w or TOKEN in w]
    assert not any("'gw-2' has" in w for w in warnings)  # a long one


def test_the_audit_log_says_who_registered_identified_and_deleted_a_loop(tmp_path):
    """Registrations with a gateway's token are told from the admin token's; identify and
    delete carry the actor as patch and reset do."""
    gw_token = "gateway-one-token-0123456789"
    mine = {"Authorization": f"Bearer {gw_token}"}
    with _served(tmp_path, api_token=TOKEN, api_gateway_tokens={"gw-1": gw_token}) as (_, port):
        url = f"http://127.0.0.1:{port}"
        r = httpx.post(f"{url}/loops", json=loop_body("G", gateway="gw-1"), headers=mine)
        assert r.status_code == 201, r.text
        pair = [loop_body("H", gateway="gw-1")]
        assert httpx.post(f"{url}/loops/bulk", headers=mine, json=pair).status_code == 201
        httpx.post(f"{url}/loops", json=loop_body("L"), headers=AUTH).raise_for_status()
        httpx.post(f"{url}/loops/L/identify", headers=AUTH).raise_for_status()
        httpx.delete(f"{url}/loops/L", headers=AUTH).raise_for_status()
        assert _actors(url, "G") == {"registered": "gateway:gw-1"}
        assert _actors(url, "H") == {"registered": "gateway:gw-1"}
        assert _actors(url, "L") == {"registered": "api", "identify": "api", "deleted": "api"}
        [registered] = httpx.get(f"{url}/loops/G/history").json()["items"]
        assert json.loads(registered["detail"])["gateway"] == "gw-1"  # the config is kept


def test_concurrent_wrong_logins_are_limited_too(tmp_path):
    """60 wrong console logins at once all pass the gate before any has failed; the
    login looks again once it has the form, so only MAX_FAILURES are tried."""

    async def burst(port: int) -> list[int]:
        limits = httpx.Limits(max_connections=60)
        async with httpx.AsyncClient(timeout=60.0, limits=limits) as c:
            url = f"http://127.0.0.1:{port}/ui/login"
            replies = await asyncio.gather(
                *(c.post(url, data={"token": f"guess-{k}"}) for k in range(60))
            )
            return [r.status_code for r in replies]

    with _served(tmp_path, api_token=TOKEN) as (_, port):
        codes = asyncio.run(burst(port))
    assert codes.count(303) == MAX_FAILURES and codes.count(429) == 60 - MAX_FAILURES


def test_a_malformed_host_or_origin_is_refused_not_a_server_error(tmp_path):
    with _served(tmp_path) as (_, port):
        url = f"http://127.0.0.1:{port}"
        assert httpx.get(f"{url}/loops", headers={"Host": "[::1"}).status_code == 400
        r = httpx.post(f"{url}/loops/X/reset", headers={"Origin": "http://[evil"})
        assert r.status_code == 403


GW_A, GW_B = "gateway-A-token-0123456789", "gateway-B-token-0123456789"
SQUATTED = "unitB-FIC-101"
"""gw-B's loop, whose id gw-A's token registered first as gw-A's (a security review)."""


@contextlib.contextmanager
def _squatted(tmp_path):
    """The API with gateways gw-A and gw-B, gw-B's loop id taken by gw-A's token with
    wide limits: the tuner, the URL."""
    tokens = {"gw-A": GW_A, "gw-B": GW_B}
    with _served(tmp_path, api_token=TOKEN, api_gateway_tokens=tokens) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        wide = loop_body(SQUATTED, gateway="gw-A", guard={"kp_max": 1000.0, "ki_max": 1000.0})
        r = httpx.post(f"{url}/loops", json=wide, headers={"Authorization": f"Bearer {GW_A}"})
        assert r.status_code == 201, r.text
        yield tuner, url


def test_a_taken_id_is_refused_naming_the_gateway_of_its_loop(tmp_path):
    """gw-B's registration of an id gw-A's loop holds is a 409 that names gw-A (so gw-B's
    client can tell it from its own loop registered before), and nothing else of it."""
    with _squatted(tmp_path) as (tuner, url):
        b = {"Authorization": f"Bearer {GW_B}"}
        httpx.post(f"{url}/loops", json=loop_body("OPEN"), headers=AUTH).raise_for_status()
        mine = loop_body("unitB-FIC-102", gateway="gw-B")
        httpx.post(f"{url}/loops", json=mine, headers=b).raise_for_status()
        r = httpx.post(f"{url}/loops", json=loop_body(SQUATTED, gateway="gw-B"), headers=b)
        assert r.status_code == 409
        assert r.json() == {
            "detail": f"loop already registered: '{SQUATTED}' (gateway 'gw-A')",
            "gateways": {SQUATTED: "gw-A"},
        }
        bulk = [loop_body(i, gateway="gw-B") for i in ("NEW", SQUATTED, "unitB-FIC-102")]
        r = httpx.post(f"{url}/loops/bulk", json=bulk, headers=b)
        assert r.status_code == 409
        assert r.json()["gateways"] == {SQUATTED: "gw-A", "unitB-FIC-102": "gw-B"}
        r = httpx.post(f"{url}/loops", json=loop_body("OPEN"), headers=AUTH)
        assert r.status_code == 409 and r.json()["gateways"] == {"OPEN": None}
        assert "1000" not in r.text  # no config of the loop
        assert sorted(tuner.loop_ids()) == ["OPEN", SQUATTED, "unitB-FIC-102"]
        assert tuner.view(SQUATTED).config.gateway == "gw-A"


def test_a_gateways_client_refuses_an_id_another_gateways_loop_took(tmp_path, monkeypatch):
    """The OPC UA gateway's and the plant simulator's registrations took any 409 for
    "known, carry on": gw-B's loop, whose id gw-A held, was then never tuned (its samples
    rejected wrong_gateway), unreported. Now a RegistrationError names both gateways; a
    loop of its own registered before still carries on."""
    monkeypatch.setenv("PITUNE_TEST_GW_TOKEN", GW_B)
    with _squatted(tmp_path) as (tuner, url):
        site = parse_map({
            "server": {"url": "opc.tcp://127.0.0.1:4840", "security": "None",
                       "allow_insecure": True},
            "bus": {"gateway_id": "gw-B"},
            "tuner": {"register_url": url, "token_env": "PITUNE_TEST_GW_TOKEN",
                      "timeout_s": 10.0},
            "loops": [{"id": "L", "sp": "ns=2;s=sp", "pv": "ns=2;s=pv", "p": "ns=2;s=p",
                       "i": "ns=2;s=i", "limits": {"p": [0.1, 10.0], "i": [0.1, 10.0]}}],
        })  # fmt: skip
        own = [loop_body(i, gateway="gw-B") for i in ("unitB-FIC-102", "unitB-FIC-103")]
        assert register_loops(site, own) == 2
        assert register_loops(site, own) == 0  # a restart: its own loops, known
        both = f"'{SQUATTED}' is already registered with gateway 'gw-A', not this gateway 'gw-B'"
        with pytest.raises(RegistrationError, match=both):
            register_loops(site, [*own, loop_body(SQUATTED, gateway="gw-B")])
        specs = (LoopSpec("two_tank", "unitB-FIC-104"), LoopSpec("two_tank", SQUATTED))
        with pytest.raises(RegistrationError, match=both):
            register(url, specs, scan=1.0, token=GW_B, timeout=10.0, gateway="gw-B")
        assert sorted(register(url, specs[:1], scan=1.0, token=GW_B, timeout=10.0,
                               gateway="gw-B")) == ["unitB-FIC-104"]  # fmt: skip
        assert tuner.view(SQUATTED).config.gateway == "gw-A"


def test_behind_a_tls_proxy_the_browsers_origin_is_the_apis_by_its_allowed_host(tmp_path):
    """nginx's proxy_pass passes its upstream's Host (127.0.0.1:PORT): the browser's
    Origin https://tuner.plant.example was refused (403) at the console's login. It is
    the API's own when its host is an allowed host set by name and its scheme is the one
    a trusted proxy forwarded; a wildcard host lets no other page through."""
    proxy = {"X-Forwarded-Proto": "https", "X-Forwarded-For": "10.0.0.5"}
    hosts = ["127.0.0.1", "tuner.plant.example", "*"]
    login = {"token": TOKEN, "next": "/ui"}

    def answers(url: str, *origins: str, headers=proxy) -> list[int]:
        return [
            httpx.post(f"{url}/ui/login", data=login, headers={**headers, "Origin": o}).status_code
            for o in origins
        ]  # fmt: skip

    trusted = {"api_trusted_proxies": ["127.0.0.1"], "api_allowed_hosts": hosts}
    with _served(tmp_path, api_token=TOKEN, **trusted) as (_, port):
        url = f"http://127.0.0.1:{port}"
        r = httpx.post(f"{url}/ui/login", data=login,
                       headers={**proxy, "Origin": "https://tuner.plant.example"})  # fmt: skip
        assert r.status_code == 303 and r.headers["location"] == "/ui", r.text
        assert "secure" in r.headers["set-cookie"].lower()  # the https the proxy reported
        assert answers(url, "https://tuner.plant.example:8443") == [303]  # the proxy's port
        refused = ("http://tuner.plant.example", "https://evil.example", "https://*", "null")
        assert answers(url, *refused) == [403] * 4
        # no forwarded scheme: not through the proxy
        assert answers(url, "https://tuner.plant.example", headers={}) == [403]
        r = httpx.post(
            f"{url}/loops/X/reset", headers={**AUTH, **proxy, "Origin": "https://evil.example"}
        )
        assert r.status_code == 403
    # the same from a proxy not named in api_trusted_proxies: its scheme is not believed
    untrusted = {"api_allowed_hosts": hosts}
    with _served(tmp_path / "b", api_token=TOKEN, **untrusted) as (_, port):
        assert answers(f"http://127.0.0.1:{port}", "https://tuner.plant.example") == [403]
