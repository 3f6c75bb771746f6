"""The plant-wide hold in the console: the hold and release actions (a console session,
the actor ``ui:<name>``, a bad reason a 422 on one line that changes nothing), the
hold's stream every page's banner follows."""

from __future__ import annotations

import json
import time

import httpx
import pytest

from service.daemon.console.screenshots import serve
from tests import test_console_api as console_api
from tests.test_console_api import client, login  # noqa: F401 - a fixture
from tests.tuner_support import loop_body, tuner_settings

RELEASED = {"held": False, "since": None, "by": None, "reason": None}


@pytest.mark.parametrize(
    ("reason", "says"),
    [
        ("", "reason: String should have at least 1 character"),
        ("x" * 201, "reason: String should have at most 200 characters"),
        ("two\nlines", "the reason must be printable text on one line: U+000A at 3"),
        ("   ", "the reason must say something: it is blank"),
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
