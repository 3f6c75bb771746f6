"""The plant-wide hold in the console: the hold and release actions (a console session,
the actor ``ui:<name>``, a bad reason a 422 on one line that changes nothing), the
hold's stream every page's banner follows, and, in headless Chromium against the real
daemon, the banner, the tuner page's control and record, and a loop page's badge."""

from __future__ import annotations

import datetime
import json
import time

import httpx
import pytest

from service.daemon.console.screenshots import serve
from tests import test_console_api as console_api
from tests.browser import *  # noqa: F403 - the fixtures
from tests.test_console_api import client, login  # noqa: F401 - a fixture
from tests.test_console_browser import BEARER, logged_in
from tests.tuner_support import loop_body, tuner_settings

RELEASED = {"held": False, "since": None, "by": None, "reason": None}
NOT_CHANGED = "No loop's gains change while held"


@pytest.mark.parametrize(
    ("reason", "says"),
    [
        ("", "reason: String should have at least 1 character"),
        ("x" * 201, "reason: String should have at most 200 characters"),
        ("two\nlines", "the reason must be printable text on one line: U+000A at 3"),
        ("   ", "the reason must say something: it has no letter or digit"),
        ("\u2800\u2800", "the reason must say something: it has no letter or digit"),
    ],
)
def test_a_bad_reason_from_the_console_is_a_422_on_one_line_and_changes_nothing(
    client,  # noqa: F811 - the fixture
    reason,
    says,
):
    ok = {"X-CSRF-Token": login(client)}
    r = client.post("/ui/api/hold", json={"reason": reason}, headers=ok)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert isinstance(detail, str) and says in detail and "\n" not in detail, detail
    assert client.get("/hold").json() == RELEASED
    assert client.get("/hold/history").json() == []


def test_the_console_holds_and_releases_as_the_logged_in_operator(client):  # noqa: F811
    body = {"reason": "unit 2 start-up"}
    assert client.post("/ui/api/hold", json=body).status_code == 401  # no session
    ok = {"X-CSRF-Token": login(client, "alice")}
    assert client.post("/ui/api/hold", json=body, headers={"X-CSRF-Token": "x"}).status_code == 403
    other = {**ok, "Origin": "http://evil.example"}
    assert client.post("/ui/api/hold", json=body, headers=other).status_code == 403
    assert client.post("/ui/api/hold/release", headers=other).status_code == 403
    assert client.get("/hold").json() == RELEASED

    began = time.time()
    r = client.post("/ui/api/hold", json=body, headers=ok)
    assert r.status_code == 200, r.text
    held = r.json()
    assert (held["held"], held["by"], held["reason"]) == (True, "ui:alice", "unit 2 start-up")
    assert began <= held["since"] <= time.time()
    assert client.get("/hold").json() == held
    r = client.post("/ui/api/hold/release", headers=ok)
    assert r.status_code == 200 and r.json() == RELEASED
    assert client.get("/hold").json() == RELEASED
    events = client.get("/hold/history").json()
    assert [(e["action"], e["by"], e["reason"]) for e in events] == [
        ("release", "ui:alice", "unit 2 start-up"),
        ("hold", "ui:alice", "unit 2 start-up"),
    ]


def test_a_loop_pages_data_carries_the_plant_hold(client):  # noqa: F811
    client.post("/loops", json=loop_body("L1"), headers=console_api.BEARER)
    assert client.get("/ui/api/loops/L1/recent").json()["plant"] == RELEASED
    ok = {"X-CSRF-Token": login(client)}
    client.post("/ui/api/hold", json={"reason": "upset"}, headers=ok).raise_for_status()
    data = client.get("/ui/api/loops/L1/recent").json()
    assert data["plant"] == client.get("/hold").json() and data["plant"]["held"]
    assert data["live"]["hold"]["guard"] == "plant"
    assert client.get("/ui/api/loops/nope/recent").status_code == 404


def _sse(url: str, deadline: float):
    """The data of each message of the stream at ``url``, across its renewals (``bye``)."""
    while time.monotonic() < deadline:
        with httpx.stream("GET", url, timeout=30) as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            kind = "message"
            for line in r.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind == "message":
                    yield json.loads(line[6:])
                elif line == "":
                    kind = "message"
    raise AssertionError("the stream did not say it in time")


def test_the_hold_stream_sends_the_hold_at_once_and_at_each_change(tmp_path):
    """Over a real socket: the hold when the stream opens, then each hold, change of
    reason and release, once each (none repeated while nothing changes)."""
    with serve(tuner_settings(tmp_path)) as daemon:
        url = f"{daemon.url}/hold"
        changes = iter([
            lambda: httpx.put(url, json={"reason": "first"}),
            lambda: httpx.put(url, json={"reason": "second"}),
            lambda: httpx.delete(url),
        ])  # fmt: skip
        seen = []
        for plant in _sse(f"{daemon.url}/ui/api/hold/stream", time.monotonic() + 60.0):
            if seen and plant == seen[-1]:
                continue  # the first message of a renewed stream
            seen.append(plant)
            step = next(changes, None)
            if step is None:
                break
            step().raise_for_status()
    assert [(p["held"], p["reason"]) for p in seen] == [
        (False, None), (True, "first"), (True, "second"), (False, None)
    ]  # fmt: skip
    assert seen[1]["since"] == seen[2]["since"] and seen[1]["by"] == "api"


# -- in the browser ---------------------------------------------------------------------
def _utc(wall: float) -> str:
    """A wall time as the banner shows it."""
    return datetime.datetime.fromtimestamp(wall, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _banner(page):
    return page.locator("#hold-banner:not([hidden])")


def test_a_hold_made_through_the_api_shows_on_open_pages_and_goes_at_its_release(daemon, new_page):
    """The overview, a loop page and the tuner page, open before the hold: each shows the
    banner (who, since when in UTC, the reason as text, what it stops) without a reload,
    and hides it at the release."""
    httpx.post(f"{daemon.url}/loops", json=loop_body("L1"), headers=BEARER).raise_for_status()
    pages = [new_page() for _ in range(3)]
    for page, path in zip(pages, ("/ui", "/ui/loops/L1", "/ui/tuner"), strict=True):
        page.goto(f"{daemon.url}{path}")
    pages[0].locator('#loops tbody tr[data-id="L1"]').wait_for()
    pages[1].locator("#now dd").first.wait_for()
    pages[2].locator("body[data-loaded='1']").wait_for()
    assert all(page.locator("#hold-banner").is_hidden() for page in pages)

    reason = 'unit 2 <b>start-up</b> & "upset"'  # shown as typed, never as markup
    r = httpx.put(f"{daemon.url}/hold", json={"reason": reason}, headers=BEARER)
    held = r.raise_for_status().json()
    for page in pages:
        banner = _banner(page)
        banner.wait_for()
        text = banner.inner_text()
        assert f"since {_utc(held['since'])}, set by api: {reason}." in text, text
        assert NOT_CHANGED in text and "operators' own actions excepted" in text
        assert banner.locator("b").count() == 0
        assert page.locator("#hold-banner-reason").inner_text() == reason

    httpx.delete(f"{daemon.url}/hold", headers=BEARER).raise_for_status()
    for page in pages:
        page.locator("#hold-banner[hidden]").wait_for(state="attached")


def test_the_tuner_pages_hold_button_holds_with_the_reason_as_the_operator(daemon, new_page):
    """Logged in as alice: a missing or overlong reason is refused on the page (nothing
    sent), a reason the server refuses shows its 422 on one line, a good one holds the
    plant as ui:alice and appears in the record; Release, confirmed, releases it."""
    page = logged_in(new_page(), daemon.url, "alice")
    page.goto(f"{daemon.url}/ui/tuner")
    page.locator("#hold-history tbody tr").first.wait_for()
    assert page.locator("#hold-history tbody").inner_text() == "never held"
    assert page.locator("#hold-release").is_hidden()
    error = page.locator("#hold-error")

    page.click("#hold-all")
    page.locator('#hold-error:text("a reason is required")').wait_for()
    page.fill("#hold-reason", "x" * 201)
    page.click("#hold-all")
    page.locator('#hold-error:text("at most 200 characters (201)")').wait_for()
    page.fill("#hold-reason", "two\tcolumns")
    page.click("#hold-all")
    page.locator('#hold-error:text("printable text on one line only: U+0009 at 3")').wait_for()
    assert httpx.get(f"{daemon.url}/hold").json() == RELEASED  # nothing sent

    # a client whose check lets through what the server's refuses: the server's 422
    def tampered(route):
        route.continue_(post_data=json.dumps({"reason": "a\u202eb"}))

    page.route("**/ui/api/hold", tampered)
    page.fill("#hold-reason", "fine here")
    page.click("#hold-all")
    page.locator('#hold-error:text("refused (422: reason:")').wait_for()
    shown = error.inner_text()
    assert "U+202E at 1" in shown and "\n" not in shown, shown
    page.unroute("**/ui/api/hold", tampered)
    # whether a reason says something is the server's rule alone: its 422 shown
    page.fill("#hold-reason", "   ")
    page.click("#hold-all")
    page.locator('#hold-error:text("it has no letter or digit")').wait_for()
    assert error.inner_text().startswith("refused (422: reason:"), error.inner_text()
    assert httpx.get(f"{daemon.url}/hold").json() == RELEASED

    page.fill("#hold-reason", "DCS change window")
    page.click("#hold-all")
    _banner(page).wait_for()
    held = httpx.get(f"{daemon.url}/hold").json()
    assert (held["held"], held["by"], held["reason"]) == (True, "ui:alice", "DCS change window")
    assert "set by ui:alice: DCS change window." in _banner(page).inner_text()
    assert error.inner_text() == ""
    row = page.locator('#hold-history tbody tr[data-action="hold"]')
    row.wait_for()
    assert row.locator("td").all_inner_texts() == [
        _utc(held["since"]).removesuffix(" UTC"), "hold", "ui:alice", "DCS change window"
    ]  # fmt: skip
    assert page.locator("#hold-all").inner_text() == "Change the reason"

    page.once("dialog", lambda d: d.accept())
    page.click("#hold-release")
    page.locator("#hold-banner[hidden]").wait_for(state="attached")
    assert httpx.get(f"{daemon.url}/hold").json() == RELEASED
    page.locator('#hold-history tbody tr[data-action="release"]').wait_for()
    events = httpx.get(f"{daemon.url}/hold/history").json()
    assert [(e["action"], e["by"]) for e in events] == [
        ("release", "ui:alice"), ("hold", "ui:alice")
    ]  # fmt: skip
    page.locator("#hold-release[hidden]").wait_for(state="attached")


def test_a_loop_under_the_hold_names_the_plant_hold(daemon, new_page):
    """A loop page and the overview under the plant-wide hold say so (the badge was the
    model check's for any hold but a cool-down), the loop page's badge with its why."""
    httpx.post(f"{daemon.url}/loops", json=loop_body("L1"), headers=BEARER).raise_for_status()
    httpx.put(f"{daemon.url}/hold", json={"reason": "upset"}, headers=BEARER).raise_for_status()
    why = httpx.get(f"{daemon.url}/loops/L1").json()["hold"]["why"]
    page = new_page()
    page.goto(f"{daemon.url}/ui/loops/L1")
    badge = page.locator('#hold[data-guard="plant"]:not([hidden])')
    badge.wait_for()
    assert badge.inner_text() == "held: plant-wide hold"
    assert badge.get_attribute("title") == why
    _banner(page).wait_for()
    page.goto(f"{daemon.url}/ui")
    row = page.locator('#loops tbody tr[data-id="L1"]')
    row.wait_for()
    assert row.locator(".badge.hold").inner_text() == "held: plant-wide hold"
