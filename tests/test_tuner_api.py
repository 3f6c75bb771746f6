"""The admin API: the real FastAPI app (lifespan, tuner, Zenoh) through TestClient."""

import logging

import pytest
from fastapi.testclient import TestClient

from service.daemon.api import create_app
from tests.tuner_support import loop_body, tuner_settings

pytestmark = pytest.mark.timeout(60)
TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(tuner_settings(tmp_path, api_token=TOKEN))) as c:
        yield c


@pytest.fixture
def open_client(tmp_path):
    """No token configured: mutating calls are open."""
    with TestClient(create_app(tuner_settings(tmp_path))) as c:
        yield c


def test_register_inspect_patch_reset_delete(client):
    r = client.post("/loops", json=loop_body("LIC-101"), headers=AUTH)
    assert r.status_code == 201, r.text
    view = r.json()
    assert (view["kp"], view["ki"], view["mode"], view["status"]) == (0.5, 0.01, "auto", "waiting")
    assert view["rl_period_s"] == pytest.approx(165.0)
    assert view["scaling"] == pytest.approx({"e_scale": 0.1, "u_scale": 0.24, "time_unit_s": 60.0})
    guard = view["config"]["guard"]
    assert guard["kp_min"] == pytest.approx(0.01 * 0.1 / 0.24)  # agent range, mapped
    assert guard["ki_max"] == pytest.approx(50.0 * 0.1 / 0.24 / 60.0)
    zero = {"samples": 0, "rejected": 0, "steps": 0, "updates": 0, "quiet": 0, "faults": 0}
    assert {k: view["counters"].get(k) for k in zero} == zero  # the engine may add more

    assert client.post("/loops", json=loop_body("LIC-101"), headers=AUTH).status_code == 409
    client.post("/loops", json=loop_body("FIC-7", mode="frozen"), headers=AUTH)
    assert [v["config"]["id"] for v in client.get("/loops").json()["items"]] == [
        "LIC-101",
        "FIC-7",
    ]

    r = client.patch("/loops/LIC-101", json={"mode": "advisory", "kp_max": 2.0}, headers=AUTH)
    assert r.status_code == 200, r.text
    assert r.json()["mode"] == "advisory" and r.json()["config"]["guard"]["kp_max"] == 2.0
    r = client.patch("/loops/LIC-101", json={"kp_min": 5.0}, headers=AUTH)
    assert r.status_code == 422 and "min < max" in r.json()["detail"]
    assert client.get("/loops/LIC-101").json()["config"]["guard"]["kp_min"] == guard["kp_min"]

    r = client.post("/loops/LIC-101/reset", headers=AUTH)
    assert r.status_code == 200 and r.json()["seq"] == 1

    metrics = client.get("/metrics").text
    assert 'pitune_loops{mode="advisory"} 1.0' in metrics
    assert 'pitune_loops{mode="frozen"} 1.0' in metrics
    # no samples yet: one loop waiting, the frozen one frozen, every status listed
    assert 'pitune_loops_by_status{status="waiting"} 1.0' in metrics
    assert 'pitune_loops_by_status{status="frozen"} 1.0' in metrics
    assert 'pitune_loops_by_status{status="quiet"} 0.0' in metrics
    assert 'pitune_updates_published_total{mode="advisory"} 1.0' in metrics  # the reset

    assert client.delete("/loops/LIC-101", headers=AUTH).status_code == 204
    assert client.get("/loops/LIC-101").status_code == 404
    assert client.delete("/loops/LIC-101", headers=AUTH).status_code == 404
    history = client.get("/loops/LIC-101/history").json()  # the log outlives the loop
    reasons = [e["reason"] for e in history["items"]]
    assert reasons == ["deleted", "reset", "patched", "registered"]
    assert history["items"][1]["kp_new"] == 0.5


def test_history_is_paginated_newest_first(open_client):
    client = open_client
    client.post("/loops", json=loop_body("L1"))
    for _ in range(5):
        client.post("/loops/L1/reset")
    page = client.get("/loops/L1/history", params={"offset": 1, "limit": 2}).json()
    assert page["total"] == 6 and (page["offset"], page["limit"]) == (1, 2)
    assert [e["seq"] for e in page["items"]] == [4, 3]
    assert client.get("/loops/L1/history", params={"limit": 0}).status_code == 422
    assert client.get("/loops/nope/history").status_code == 404


MUTATIONS = [
    ("post", "/loops", loop_body("NEW")),
    ("patch", "/loops/LIC-101", {"mode": "frozen"}),
    ("post", "/loops/LIC-101/reset", None),
    ("delete", "/loops/LIC-101", None),
]


@pytest.mark.parametrize(
    "headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN}]
)
def test_mutations_without_the_token_are_refused_and_change_nothing(client, headers):
    client.post("/loops", json=loop_body("LIC-101"), headers=AUTH)
    before = (
        client.get("/loops").json(),
        client.get("/loops/LIC-101/history").json(),
    )
    for method, path, body in MUTATIONS:
        kwargs = {"json": body} if body is not None else {}
        r = client.request(method, path, headers=headers, **kwargs)
        assert r.status_code == 401, (method, path, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
        assert "token" in r.json()["detail"]
    assert (
        client.get("/loops").json(),
        client.get("/loops/LIC-101/history").json(),
    ) == before
    # reads need no token, like the probes and metrics
    for path in ("/loops", "/loops/LIC-101", "/loops/LIC-101/history", "/metrics"):
        assert client.get(path, headers=headers).status_code == 200, path


@pytest.mark.parametrize(
    ("body", "field"),
    [
        (loop_body("bad/id"), "id"),
        (loop_body(kp=-1.0), "kp"),
        (loop_body(ki=float("inf")), "ki"),
        (loop_body(scaling={"k_hat": 1.0}), "scaling"),
        (loop_body(guard={"kp_max": 0.1}), "bounds"),  # registered kp above the bound
        (loop_body(forgetting=1.5), "forgetting"),
        (loop_body(gateway="gw/north"), "gateway"),  # one key-expression chunk
        (loop_body(extra=1), "extra"),
    ],
)
def test_invalid_registrations_get_422_with_a_message(open_client, body, field):
    r = open_client.post(
        "/loops", content=_json(body), headers={"content-type": "application/json"}
    )
    assert r.status_code == 422
    assert field in r.text
    assert open_client.get("/loops").json()["items"] == []


def _json(body: dict) -> str:
    import json

    return json.dumps(body, allow_nan=True)


def test_health_readiness_metrics_and_docs(open_client):
    client = open_client
    assert client.get("/healthz").json() == {"status": "ok", "detail": ""}
    assert client.get("/readyz").status_code == 200
    metrics = client.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain")
    for name in (
        "pitune_samples_received_total",
        'pitune_samples_rejected_total{reason="flood"}',
        "pitune_updates_published_total",
        "pitune_inference_batch_seconds_bucket",
        'pitune_loops{mode="auto"}',
    ):
        assert name in metrics.text
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    assert {
        "/loops",
        "/loops/{loop_id}",
        "/loops/{loop_id}/reset",
        "/loops/{loop_id}/history",
    } <= set(paths)


def test_after_shutdown_the_tuner_is_not_ready(tmp_path):
    app = create_app(tuner_settings(tmp_path))
    with TestClient(app) as client:
        assert client.get("/readyz").status_code == 200
        tuner = app.state.tuner
    assert not tuner.ready and not tuner.alive


def test_bulk_registration_is_all_or_nothing(client, tmp_path):
    bodies = [loop_body(f"L{i}") for i in range(50)]
    assert client.post("/loops/bulk", json=bodies).status_code == 401  # needs the token
    r = client.post("/loops/bulk", json=bodies, headers=AUTH)
    assert r.status_code == 201, r.text
    assert r.json() == {"registered": [f"L{i}" for i in range(50)]}
    views = client.get("/loops").json()["items"]
    assert len(views) == 50 and views[7]["kp"] == 0.5 and views[7]["status"] == "waiting"
    assert client.get("/loops/L7/history").json()["items"][0]["reason"] == "registered"
    assert client.get("/metrics").text.count('pitune_loops{mode="auto"} 50.0') == 1
    # one taken id, or one id twice, or one invalid body: nothing is registered
    for batch, code in (
        ([loop_body("NEW1"), loop_body("L3")], 409),
        ([loop_body("NEW1"), loop_body("NEW1")], 422),  # bad input, not a conflict
        ([loop_body("NEW1"), loop_body("bad/id")], 422),
        ([], 422),
    ):
        assert client.post("/loops/bulk", json=batch, headers=AUTH).status_code == code
        assert client.get("/loops/NEW1").status_code == 404
    assert client.get("/loops").json()["total"] == 50


@pytest.mark.parametrize("bulk", [False, True])
def test_seq_keeps_rising_when_a_loop_is_deleted_and_registered_again(tmp_path, bulk):
    """Gateways drop a seq not above the last one from the same tuner."""
    settings = tuner_settings(tmp_path)

    with TestClient(create_app(settings)) as client:
        client.post("/loops", json=loop_body("L1"))
        for _ in range(2):
            client.post("/loops/L1/reset")
        client.delete("/loops/L1")
    with TestClient(create_app(settings)) as client:  # across a restart, too
        if bulk:
            r = client.post("/loops/bulk", json=[loop_body("L1"), loop_body("NEW")])
        else:
            r = client.post("/loops", json=loop_body("L1"))
        assert r.status_code == 201
        assert client.get("/loops/L1").json()["seq"] == 2
        assert client.post("/loops/L1/reset").json()["seq"] == 3
        items = client.get("/loops/L1/history").json()["items"]
        assert [(e["reason"], e["seq"]) for e in items[:3]] == [
            ("reset", 3), ("registered", 2), ("deleted", 2)
        ]  # fmt: skip
        if bulk:
            assert client.get("/loops/NEW").json()["seq"] == 0


@pytest.mark.parametrize(
    ("host", "token", "warned"),
    [
        ("0.0.0.0", None, True),
        ("10.1.2.3", "", True),  # an empty token is none
        ("tuner.plant.local", None, True),
        ("0.0.0.0", TOKEN, False),
        ("127.0.0.1", None, False),
        ("::1", None, False),
        ("localhost", None, False),
    ],
)
def test_an_open_api_on_a_non_loopback_address_is_announced(tmp_path, caplog, host, token, warned):
    settings = tuner_settings(tmp_path, api_host=host, api_token=token)
    caplog.set_level(logging.WARNING, logger="pitune.api")
    with TestClient(create_app(settings)) as client:
        r = client.post("/loops", json=loop_body("L1"))
        assert r.status_code == (401 if token else 201)
    assert any("WITHOUT A TOKEN" in r.getMessage() for r in caplog.records) == warned


def test_the_loop_list_is_paginated(open_client):
    client = open_client
    client.post("/loops/bulk", json=[loop_body(f"L{i}") for i in range(250)])
    page = client.get("/loops").json()
    assert (page["total"], page["offset"], page["limit"], len(page["items"])) == (250, 0, 100, 100)
    page = client.get("/loops", params={"offset": 240, "limit": 1000}).json()
    assert [v["config"]["id"] for v in page["items"]] == [f"L{i}" for i in range(240, 250)]
    assert client.get("/loops", params={"offset": 300}).json()["items"] == []
    for params in ({"limit": 1001}, {"limit": 0}, {"offset": -1}):
        assert client.get("/loops", params=params).status_code == 422, params


def test_identify_history_export_and_tuner_totals(client):
    """POST /loops/{id}/identify restarts identification (token needed), the history
    exports as JSON lines oldest first, and the tuner's own totals are in /metrics."""
    import json

    body = {k: v for k, v in loop_body("L1").items() if k != "scaling"}  # no hint
    assert client.post("/loops", json=body, headers=AUTH).status_code == 201
    assert client.post("/loops/L1/identify").status_code == 401
    r = client.post("/loops/L1/identify", headers=AUTH)
    assert r.status_code == 200, r.text
    assert r.json()["status"] in ("waiting", "identifying")
    assert client.post("/loops/nope/identify", headers=AUTH).status_code == 404
    client.patch("/loops/L1", json={"mode": "advisory"}, headers=AUTH)
    r = client.get("/loops/L1/history.jsonl")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-ndjson"
    rows = [json.loads(line) for line in r.text.splitlines()]
    assert [row["reason"] for row in rows][:1] == ["registered"]
    assert rows[-1]["reason"] == "patched" and [row["id"] for row in rows] == sorted(
        row["id"] for row in rows
    )
    since = client.get("/loops/L1/history.jsonl", params={"since_id": rows[0]["id"]})
    assert len(since.text.splitlines()) == len(rows) - 1
    assert client.get("/loops/nope/history.jsonl").status_code == 404
    text = client.get("/metrics").text
    for name in ("pitune_state_queries_dropped_total", "pitune_gains_superseded_total",
                 "pitune_audit_pruned_total", "pitune_queue_bytes"):  # fmt: skip
        assert f"\n{name} " in text, name


def monitor_series(text: str) -> dict[str, float]:
    """``name{label}`` -> value of the aggregate loop gauges in a /metrics text."""
    from prometheus_client.parser import text_string_to_metric_families

    names = {"pitune_loops", "pitune_loops_by_status", "pitune_loops_monitor",
             "pitune_loops_monitor_mean"}  # fmt: skip
    return {
        f"{s.name}{{{','.join(s.labels.values())}}}": s.value
        for family in text_string_to_metric_families(text)
        if family.name in names
        for s in family.samples
    }


def test_the_aggregate_gauges_say_what_holds_once_the_last_loop_is_deleted(tmp_path):
    """A loop in manual lifts pitune_loops_monitor_mean's manual_share; once it is deleted,
    and no loop is left, no gauge keeps its numbers (they were left as the last scrape
    with a loop set them): the counts are 0 and the means NaN (a mean over no loop)."""
    import math

    from tests.tuner_support import connected_gateway, wait_until

    settings = tuner_settings(tmp_path, api_token=TOKEN)
    with TestClient(create_app(settings)) as client:
        assert client.post("/loops", json=loop_body("L1"), headers=AUTH).status_code == 201
        gw = connected_gateway(settings)
        try:
            t = iter(range(1, 10**6))

            def metrics() -> dict[str, float]:
                return monitor_series(client.get("/metrics").text)

            def manual_share() -> float:
                for _ in range(5):  # the samples of a loop in manual lift its manual share
                    gw.send("L1", {"t": float(next(t)), "e": 0.5, "auto": False})
                return metrics()["pitune_loops_monitor_mean{manual_share}"] > 0.05

            wait_until(manual_share, 20.0, "a manual share")
            held = metrics()
            assert held["pitune_loops_by_status{manual}"] == 1.0
            assert held["pitune_loops_monitor_mean{rejected_share}"] == 0.0
        finally:
            gw.close()
        assert client.delete("/loops/L1", headers=AUTH).status_code == 204
        after = metrics()
    means = {k: v for k, v in after.items() if k.startswith("pitune_loops_monitor_mean")}
    assert sorted(means) == sorted(
        f"pitune_loops_monitor_mean{{{f}}}"
        for f in ("manual_share", "saturated_share", "rejected_share", "iae_ratio")
    )
    assert all(math.isnan(v) for v in means.values()), means
    counts = {k: v for k, v in after.items() if k not in means}
    assert set(counts.values()) == {0.0}, counts
    assert len(counts) == len(held) - len(means)


def test_patch_bound_below_the_registered_gain_is_one_clear_line(client):
    """kp_max below the registered kp (0.5): a 422 whose detail is one line naming the
    gain and the bounds, not pydantic's dump (input repr, docs URL); nothing changed."""
    client.post("/loops", json=loop_body("LIC-101"), headers=AUTH)
    before = client.get("/loops/LIC-101").json()["config"]
    r = client.patch("/loops/LIC-101", json={"kp_max": 0.25}, headers=AUTH)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert detail.startswith("the registered gains must lie within the bounds: kp = 0.5 in ")
    assert "..0.25, ki = 0.01 in " in detail and detail.endswith("(nothing changed)")
    assert "\n" not in detail and "pydantic" not in detail and "input_value" not in detail
    assert client.get("/loops/LIC-101").json()["config"] == before
    r = client.patch("/loops/LIC-101", json={"kp_min": 1.0, "kp_max": 0.5}, headers=AUTH)
    assert r.json()["detail"].startswith("bounds must satisfy min < max: kp 1..0.5, ki ")
