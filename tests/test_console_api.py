"""The console's routes without a browser: pages, assets, sessions, CSRF, the overview's
server-side filter/sort/search, the tuner's figures (a real tuner, in-process)."""

from __future__ import annotations

import re
import time

import pytest
from fastapi.testclient import TestClient

from service.daemon.api import create_app
from service.daemon.console.screenshots import with_console
from service.daemon.recent import attach
from tests.tuner_support import loop_body, tuner_settings

TOKEN = "console-secret"
BEARER = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def client(tmp_path):
    app = with_console(create_app(tuner_settings(tmp_path, api_token=TOKEN)))
    with TestClient(app) as c:
        attach(app.state.tuner)
        yield c


def csrf_of(page: str) -> str:
    return re.search(r'name="pitune-csrf" content="([^"]*)"', page).group(1)


def login(client, name="alice") -> str:
    r = client.post("/ui/login", data={"token": TOKEN, "name": name}, follow_redirects=False)
    assert r.status_code == 303
    return csrf_of(client.get("/ui").text)


def test_pages_and_vendored_assets_with_licence(client):
    client.post("/loops", json=loop_body("L1"), headers=BEARER)
    for path in ("/ui", "/ui/loops/L1", "/ui/tuner", "/ui/login"):
        r = client.get(path)
        assert r.status_code == 200 and "<!doctype html>" in r.text
        assert "http://" not in r.text and "https://" not in r.text  # nothing from a CDN
        assert "script-src 'self'" in r.headers["content-security-policy"]
    assert "Unknown loop" in client.get("/ui/loops/nope").text
    js = client.get("/ui/static/vendor/uplot/uPlot.iife.min.js")
    assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript")
    assert "MIT" in client.get("/ui/static/vendor/uplot/LICENSE").text
    for bad in ("/ui/static/../routes.py", "/ui/static/%2e%2e/routes.py", "/ui/static/x.py"):
        assert client.get(bad).status_code == 404
    assert "/ui" not in client.get("/openapi.json").text  # not part of the REST API


def test_actions_need_a_session_and_its_csrf_token_and_record_the_actor(client):
    client.post("/loops", json=loop_body("L1"), headers=BEARER)
    assert client.post("/ui/api/loops/L1/patch", json={"mode": "advisory"}).status_code == 401
    r = client.post("/ui/login", data={"token": "wrong"}, follow_redirects=False)
    assert r.status_code == 303 and "error=wrong_token" in r.headers["location"]
    r = client.post("/ui/login", data={"token": TOKEN, "name": "alice"}, follow_redirects=False)
    cookie = r.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/ui" in cookie
    assert TOKEN not in cookie
    # no Max-Age: the browser would drop a session in use 8 h after its login; the
    # daemon ends it after 8 h without use (and the browser when it closes)
    assert "max-age" not in cookie.lower() and "expires" not in cookie.lower()
    csrf = csrf_of(client.get("/ui").text)
    assert client.post("/ui/api/loops/L1/patch", json={"mode": "advisory"}).status_code == 403
    wrong = {"X-CSRF-Token": "x" * len(csrf)}
    assert client.post("/ui/api/loops/L1/reset", headers=wrong).status_code == 403
    other = {"X-CSRF-Token": csrf, "Origin": "http://evil.example"}
    assert client.post("/ui/api/loops/L1/reset", headers=other).status_code == 403
    ok = {"X-CSRF-Token": csrf}
    r = client.post("/ui/api/loops/L1/patch", json={"mode": "advisory"}, headers=ok)
    assert r.status_code == 200 and r.json()["mode"] == "advisory"
    r = client.post("/ui/api/loops/L1/patch", json={"kp_min": 1e6}, headers=ok)
    assert r.status_code == 422 and "bounds" in r.json()["detail"]
    assert client.post("/ui/api/loops/L1/patch", json={"bogus": 1}, headers=ok).status_code == 422
    assert client.post("/ui/api/loops/nope/reset", headers=ok).status_code == 404
    assert client.post("/ui/api/loops/L1/reset", headers=ok).status_code == 200
    history = client.get("/loops/L1/history").json()["items"]
    assert [h["reason"] for h in history[:2]] == ["reset", "patched"]
    tuner = client.app.state.tuner
    import inspect

    if "actor" in inspect.signature(tuner.patch).parameters:  # the daemon's integration
        assert "ui:alice" in history[1]["detail"]
    r = client.post("/ui/logout", data={"csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303
    assert client.post("/ui/api/loops/L1/reset", headers=ok).status_code == 401


def test_logout_needs_the_csrf_token_and_login_refuses_foreign_origins_and_redirects(client):
    csrf = login(client)
    assert client.post("/ui/logout", data={"csrf": "nope"}).status_code == 403
    r = client.post("/ui/login", data={"token": TOKEN}, headers={"Origin": "http://evil"})
    assert r.status_code == 403
    for target in ("https://evil.example/ui", "//evil.example/ui", "/docs", "/ui\\@evil"):
        r = client.post("/ui/login", data={"token": TOKEN, "next": target},
                        follow_redirects=False)  # fmt: skip
        assert r.headers["location"] == "/ui"
    stale, csrf = csrf, csrf_of(client.get("/ui").text)  # a login starts a new session
    assert stale != csrf
    assert client.post("/ui/logout", data={"csrf": csrf}, follow_redirects=False).status_code == 303
    assert "id='login-link'" in client.get("/ui").text


def login_error(page: str) -> str:
    return re.search(r'<p class="error" id="login-error">(.*?)</p>', page, re.S).group(1)


def test_the_login_page_shows_its_own_error_texts_never_the_urls(client):
    """A link to the console's real login page put any text of its ``error`` parameter
    on it (a phisher's "re-enter the token at http://evil.example"); the page shows the
    text of a known code only."""
    r = client.post("/ui/login", data={"token": "wrong", "next": "/ui/tuner"},
                    follow_redirects=False)  # fmt: skip
    assert r.status_code == 303
    assert r.headers["location"] == "/ui/login?next=%2Fui%2Ftuner&error=wrong_token"
    assert login_error(client.get(r.headers["location"]).text) == "Wrong token."
    bait = "Session expired. Re-enter the token at http://evil.example/ui/login"
    for error in (bait, "wrong token", "<b>x</b>", ""):
        page = client.get("/ui/login", params={"error": error}).text
        assert login_error(page) == "", error
        assert "evil.example" not in page


def test_overview_filters_sorts_searches_and_pages_on_the_server(client):
    bodies = [loop_body(f"L-{i:03d}", kp=0.1 + i / 100, gateway="gw-a" if i % 2 else None)
              for i in range(120)]  # fmt: skip
    assert client.post("/loops/bulk", json=bodies, headers=BEARER).status_code == 201
    client.patch("/loops/L-007", json={"mode": "frozen"}, headers=BEARER)
    page = client.get("/ui/api/loops", params={"limit": 50}).json()
    assert page["total"] == page["matched"] == 120 and len(page["items"]) == 50
    assert page["items"][0]["id"] == "L-000" and page["statuses"]["frozen"] == 1
    assert page["statuses"]["waiting"] == 119 and page["modes"]["frozen"] == 1
    page = client.get("/ui/api/loops", params={"q": "l-01", "sort": "kp", "desc": True}).json()
    assert [i["id"] for i in page["items"]] == [f"L-{i:03d}" for i in range(19, 9, -1)]
    page = client.get("/ui/api/loops", params={"q": "GW-A", "offset": 50, "limit": 20}).json()
    assert page["matched"] == 60 and len(page["items"]) == 10
    assert all(i["gateway"] == "gw-a" for i in page["items"])
    page = client.get("/ui/api/loops", params={"status": "frozen"}).json()
    assert [i["id"] for i in page["items"]] == ["L-007"] and page["items"][0]["mode"] == "frozen"
    page = client.get("/ui/api/loops", params={"mode": "auto", "sort": "id", "desc": True}).json()
    assert page["matched"] == 119 and page["items"][0]["id"] == "L-119"
    assert client.get("/ui/api/loops", params={"limit": 501}).status_code == 422
    assert client.get("/ui/api/loops", params={"sort": "nonsense"}).status_code == 200


def test_tuner_figures(client):
    d = client.get("/ui/api/tuner").json()
    assert d["alive"] and d["store"]["ok"] and d["queue_depth"] == 0
    assert set(d["rejected"]) >= {"malformed_json", "unknown_loop", "out_of_order"}
    assert d["loops"]["total"] == 0 and "received" in d["rates"]
    assert d["trends_mb"] is not None


def test_stream_sends_only_new_samples_says_bye_and_resumes_from_last_event_id(tmp_path):
    """The loop page's server-sent events over a real socket, with a simulated plant."""
    import json

    import httpx

    from service.daemon.console.screenshots import SimLoop, SimPlant, serve

    with serve(tuner_settings(tmp_path)) as daemon:
        loop = SimLoop(id="S1")
        assert httpx.post(f"{daemon.url}/loops", json=loop.body(1.0)).status_code == 201
        plant = SimPlant(daemon.settings, [loop], speed=20.0).start()
        try:
            events, last_id = [], None
            started = time.monotonic()
            with httpx.stream("GET", f"{daemon.url}/ui/api/loops/S1/stream", timeout=30) as r:
                assert r.headers["content-type"].startswith("text/event-stream")
                kind, data = "message", None
                for line in r.iter_lines():
                    if line.startswith("id: "):
                        last_id = line[4:]
                    elif line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        data = json.loads(line[6:])
                    elif line == "" and data is not None:
                        events.append((kind, data))
                        kind, data = "message", None
            assert time.monotonic() - started < 10.0  # a stream ends by itself
            assert events[-1][0] == "bye"
            samples = [e for k, e in events if k == "message" and e["recent"]["t"]]
            assert len(samples) >= 2
            ts = [t for e in samples for t in e["recent"]["t"]]
            assert ts == sorted(ts) and len(ts) == len(set(ts))  # each sample once
            n = samples[-1]["recent"]["n"]
            assert last_id.split(".")[0] == str(n)
            assert samples[-1]["live"]["samples"] >= n - 5
            headers = {"Last-Event-ID": last_id}
            with httpx.stream("GET", f"{daemon.url}/ui/api/loops/S1/stream", headers=headers,
                              timeout=30) as r:  # fmt: skip
                for line in r.iter_lines():
                    if line.startswith("data: ") and json.loads(line[6:]).get("recent"):
                        first = json.loads(line[6:])["recent"]
                        break
            assert first["t"][0] > ts[-1]  # resumed after what was sent
            assert httpx.get(f"{daemon.url}/ui/api/loops/nope/stream").status_code == 404
        finally:
            plant.close()


def test_the_overview_a_loops_live_data_and_its_view_say_what_holds_it(client):
    """An operator's raise rolled back on demand: the agent is held for the cool-down
    (the status may still read tuning); the overview's row, the loop page's live data and
    the REST view name the hold, the live data and the view until when."""
    client.post("/loops", json=loop_body("L1"), headers=BEARER)
    client.post("/loops", json=loop_body("L2"), headers=BEARER)
    engine = client.app.state.tuner.engine
    for t, kp in ((1.0, 0.5), (2.0, 0.8)):  # the operator's kp 0.8 adopted: a change pending
        engine.ingest([{"loop_id": "L1", "t": t, "sp": 50.0, "pv": 49.0, "kp": kp, "ki": 0.01}])
    engine.rollback("L1")
    until = 2.0 + 8 * client.get("/loops/L1").json()["rl_period_s"]
    items = {i["id"]: i for i in client.get("/ui/api/loops").json()["items"]}
    assert items["L1"]["hold"] == "cooldown" and items["L2"]["hold"] is None
    live = client.get("/ui/api/loops/L1/recent").json()["live"]
    assert live["hold"]["guard"] == "cooldown"
    assert live["hold"]["until_t"] == pytest.approx(until, rel=1e-6)  # (float32 periods)
    assert live["oscillating"] is False
    view = client.get("/loops/L1").json()
    assert view["hold"] == live["hold"] and view["oscillating"] is False
    assert client.get("/loops/L2").json()["hold"] is None


def test_the_loop_pages_live_data_and_the_view_say_why_a_loop_is_not_tuning(client):
    """A loop its gateway reports in manual: the loop page's live data, the overview's row
    and the REST view give the same status_why (the share in manual, the next step); a
    tuning loop none."""
    client.post("/loops", json=loop_body("L1"), headers=BEARER)
    client.post("/loops", json=loop_body("L2"), headers=BEARER)
    engine = client.app.state.tuner.engine
    for t in range(4):
        engine.ingest([{"loop_id": "L1", "t": float(t), "sp": 50.0, "pv": 50.0, "kp": 0.5,
                        "ki": 0.01, "auto": False}])  # fmt: skip
        engine.ingest([{"loop_id": "L2", "t": float(t), "sp": 50.0, "pv": 50.0, "kp": 0.5,
                        "ki": 0.01}])  # fmt: skip
    live = client.get("/ui/api/loops/L1/recent").json()["live"]
    assert live["status"] == "manual"
    assert re.fullmatch(
        r"the gateway reports the loop in manual \([0-9.]+ % of the recent window\): "
        r"tuning pauses\. Next: put the loop back in auto in the DCS",
        live["status_why"],
    )
    assert client.get("/loops/L1").json()["status_why"] == live["status_why"]
    items = {i["id"]: i for i in client.get("/ui/api/loops").json()["items"]}  # tooltip
    assert items["L1"]["status_why"] == live["status_why"] and items["L2"]["status_why"] is None
    other = client.get("/ui/api/loops/L2/recent").json()["live"]
    assert other["status"] == "tuning" and other["status_why"] is None
    assert client.get("/loops/L2").json()["status_why"] is None
