"""The plant-wide hold's REST calls (service/daemon/hold_api.py): the real app under
uvicorn over HTTP, a real SQLite file. ``PUT /hold`` holds, ``DELETE /hold`` releases,
both idempotent; every loop's view says it; the metric and the log line; the record of
holds and releases; bad input and a gateway's token change nothing; the hold survives a
restart. (What it holds: tests/test_plant_hold.py, through the engine.)"""

from __future__ import annotations

import logging
import time

import httpx
import pytest

from tests.test_api_gate import AUTH, TOKEN, _served
from tests.tuner_support import loop_body

pytestmark = pytest.mark.timeout(120)
GATEWAY_TOKEN = "gateway-one-token-0123456789"
GATEWAY = {"Authorization": f"Bearer {GATEWAY_TOKEN}"}
RELEASED = {"held": False, "since": None, "by": None, "reason": None}


def _metric(url: str) -> str:
    lines = httpx.get(f"{url}/metrics").text.splitlines()
    return next(line for line in lines if line.startswith("pitune_hold "))


def test_hold_release_and_every_loops_view_metric_log_and_record(tmp_path, caplog):
    caplog.set_level(logging.INFO, "pitune.tuner")
    caplog.set_level(logging.INFO, "pitune.events")
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        for loop_id in ("A", "B"):
            httpx.post(f"{url}/loops", json=loop_body(loop_id), headers=AUTH).raise_for_status()
        assert httpx.get(f"{url}/hold").json() == RELEASED
        assert _metric(url) == "pitune_hold 0.0"
        began = time.time()
        r = httpx.put(f"{url}/hold", json={"reason": "upset on unit 2"}, headers=AUTH)
        assert r.status_code == 200, r.text
        held = r.json()
        assert held["held"] and held["by"] == "api" and held["reason"] == "upset on unit 2"
        assert began <= held["since"] <= time.time()
        assert httpx.get(f"{url}/hold").json() == held == tuner.hold.model_dump()
        assert _metric(url) == "pitune_hold 1.0"
        for loop_id in ("A", "B"):
            hold = httpx.get(f"{url}/loops/{loop_id}").json()["hold"]
            assert hold["guard"] == "plant" and "set by api at " in hold["why"]
            assert "upset on unit 2" in hold["why"] and "DELETE /hold" in hold["why"]
        assert {i["hold"]["guard"] for i in httpx.get(f"{url}/loops").json()["items"]} == {"plant"}
        warned = [r for r in caplog.records if "PLANT-WIDE HOLD set by api" in r.message]
        assert len(warned) == 1 and warned[0].levelno == logging.WARNING
        assert "upset on unit 2" in warned[0].message
        # again: the same hold, its reason replaced (who and since when kept)
        r = httpx.put(f"{url}/hold", json={"reason": "upset, unit 2 tripped"}, headers=AUTH)
        assert r.json() == {**held, "reason": "upset, unit 2 tripped"}
        r = httpx.put(f"{url}/hold", json={"reason": "upset, unit 2 tripped"}, headers=AUTH)
        assert r.json() == {**held, "reason": "upset, unit 2 tripped"}  # nothing new
        r = httpx.delete(f"{url}/hold", headers=AUTH)
        assert r.status_code == 200 and r.json() == RELEASED
        assert httpx.delete(f"{url}/hold", headers=AUTH).json() == RELEASED  # idempotent
        assert _metric(url) == "pitune_hold 0.0"
        assert httpx.get(f"{url}/loops/A").json()["hold"] is None
        released = [r for r in caplog.records if "plant-wide hold released by api" in r.message]
        assert len(released) == 1 and "upset, unit 2 tripped" in released[0].message
        # each call's caller, as every admin change's (the console's names it too)
        calls = [r.message for r in caplog.records if r.message.startswith("plant-wide hold")]
        calls = [call for call in calls if "via the API" in call]
        assert calls == [
            "plant-wide hold set: 'upset on unit 2' via the API from 127.0.0.1 as api",
            "plant-wide hold set: 'upset, unit 2 tripped' via the API from 127.0.0.1 as api",
            "plant-wide hold set: 'upset, unit 2 tripped' via the API from 127.0.0.1 as api",
            "plant-wide hold released via the API from 127.0.0.1 as api",
            "plant-wide hold released via the API from 127.0.0.1 as api",
        ]
        history = httpx.get(f"{url}/hold/history").json()
        assert [(e["action"], e["by"], e["reason"]) for e in history] == [
            ("release", "api", "upset, unit 2 tripped"),
            ("reason", "api", "upset, unit 2 tripped"),
            ("hold", "api", "upset on unit 2"),
        ]
        assert history[-1]["wall_time"] == held["since"]


@pytest.mark.parametrize(
    ("body", "says"),
    [
        (None, "Field required"),
        ({}, "Field required"),
        ({"reason": ""}, "at least 1 character"),
        ({"reason": "x" * 201}, "at most 200 characters"),
        ({"reason": "two\nlines"}, "U+000A at 3"),
        ({"reason": "\x1b[2Jclear"}, "U+001B at 0"),
        ({"reason": "abc\u202edcba"}, "U+202E at 3"),  # a bidi override
        ({"reason": "   "}, "no letter or digit"),
        # printable, but blank-looking: a Hangul filler, Braille blanks, a combining mark
        ({"reason": "\u3164"}, "no letter or digit"),
        ({"reason": "\u2800\u2800"}, "no letter or digit"),
        ({"reason": " \u0301"}, "no letter or digit"),
        ({"reason": "--- !"}, "no letter or digit"),
        ({"reason": 7}, "valid string"),
        ({"reason": "ok", "until": 3}, "Extra inputs"),
    ],
)
def test_bad_input_is_a_422_with_one_line_and_changes_nothing(tmp_path, body, says):
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        httpx.put(f"{url}/hold", json={"reason": "first"}, headers=AUTH).raise_for_status()
        before = httpx.get(f"{url}/hold").json()
        r = httpx.put(f"{url}/hold", json=body, headers=AUTH)
        assert r.status_code == 422, r.text
        (error,) = r.json()["detail"]
        assert says in error["msg"] and "\n" not in error["msg"], error
        assert httpx.get(f"{url}/hold").json() == before
        assert len(httpx.get(f"{url}/hold/history").json()) == 1


def test_the_holds_own_event_stays_on_record_however_many_reason_changes_follow(tmp_path):
    """150 changes of the reason: the record keeps the last 100 events, the last of them
    the hold's own (who held the plant, when, why), released too; before, they pushed it
    out. Held again: the older hold goes as any event does."""
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        held = httpx.put(f"{url}/hold", json={"reason": "night shift: unit 2 upset"},
                         headers=AUTH).json()  # fmt: skip
        for i in range(150):
            r = httpx.put(f"{url}/hold", json={"reason": f"{i:03d}"}, headers=AUTH)
            assert r.status_code == 200, r.text
        history = httpx.get(f"{url}/hold/history").json()
        assert len(history) == 100
        assert [e["reason"] for e in history[:-1]] == [f"{i:03d}" for i in range(149, 50, -1)]
        assert {e["action"] for e in history[:-1]} == {"reason"}
        start = {"action": "hold", "wall_time": held["since"], "by": "api",
                 "reason": "night shift: unit 2 upset"}  # fmt: skip
        assert history[-1] == start
        httpx.delete(f"{url}/hold", headers=AUTH).raise_for_status()
        history = httpx.get(f"{url}/hold/history").json()
        assert len(history) == 100 and history[0]["action"] == "release"
        assert history[-1] == start
        httpx.put(f"{url}/hold", json={"reason": "again"}, headers=AUTH).raise_for_status()
        history = httpx.get(f"{url}/hold/history").json()
        assert len(history) == 100 and [e["action"] for e in history[:2]] == ["hold", "release"]
        assert start not in history


def test_a_reason_in_any_script_or_digits_alone_is_taken(tmp_path):
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        for reason in ("停机检修", "٣", "Ⅻ", "\u3164a", "7"):
            r = httpx.put(f"{url}/hold", json={"reason": reason}, headers=AUTH)
            assert r.status_code == 200 and r.json()["reason"] == reason, r.text


def test_a_gateways_token_or_none_cannot_hold_or_release(tmp_path):
    with _served(tmp_path, api_token=TOKEN, api_gateway_tokens={"gw-1": GATEWAY_TOKEN}) as (
        tuner, port,
    ):  # fmt: skip
        url = f"http://127.0.0.1:{port}"
        body = {"reason": "a gateway's idea"}
        assert httpx.put(f"{url}/hold", json=body, headers=GATEWAY).status_code == 403
        assert httpx.put(f"{url}/hold", json=body).status_code == 401
        assert httpx.get(f"{url}/hold").json() == RELEASED
        httpx.put(f"{url}/hold", json={"reason": "ops"}, headers=AUTH).raise_for_status()
        assert httpx.delete(f"{url}/hold", headers=GATEWAY).status_code == 403
        assert httpx.delete(f"{url}/hold").status_code == 401
        assert httpx.get(f"{url}/hold").json()["reason"] == "ops"
        assert [e["by"] for e in httpx.get(f"{url}/hold/history").json()] == ["api"]


def test_the_hold_survives_a_restart_and_so_does_its_release(tmp_path, caplog):
    caplog.set_level(logging.WARNING, "pitune.tuner")
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        httpx.post(f"{url}/loops", json=loop_body("A"), headers=AUTH).raise_for_status()
        held = httpx.put(f"{url}/hold", json={"reason": "startup"}, headers=AUTH).json()
    caplog.clear()
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        assert httpx.get(f"{url}/hold").json() == held
        assert tuner.engine.table.hold.held and _metric(url) == "pitune_hold 1.0"
        assert httpx.get(f"{url}/loops/A").json()["hold"]["guard"] == "plant"
        (line,) = [r.message for r in caplog.records if "PLANT-WIDE HOLD" in r.message]
        assert "(read from the store)" in line and "startup" in line
        httpx.delete(f"{url}/hold", headers=AUTH).raise_for_status()
    with _served(tmp_path, api_token=TOKEN) as (tuner, port):
        url = f"http://127.0.0.1:{port}"
        assert httpx.get(f"{url}/hold").json() == RELEASED
        assert httpx.get(f"{url}/loops/A").json()["hold"] is None
        assert [e["action"] for e in httpx.get(f"{url}/hold/history").json()] == [
            "release", "hold"
        ]  # fmt: skip
