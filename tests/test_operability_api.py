"""Admin API and logs of an operated tuner (issues 17 and 18 item 7): documentation
served without a CDN, process metrics without ``_created`` series, pagination that
never gives a 5xx, one log format (text or JSON) for pitune and uvicorn, INFO lines of
loop changes, rate-limited."""

import io
import json
import logging
import re
import signal

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.agent import load_agent
from service.daemon import logs
from service.daemon.api import MAX_OFFSET, create_app
from service.daemon.metrics import Metrics
from service.engine import LoopConfig, TuningEngine
from service.engine.audit import audit_row
from service.engine.status import STATUSES
from service.procs import TunerProcess
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def root_logger():
    """The root logger's handlers and level, restored after a test that configures it."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    yield
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(tuner_settings(tmp_path))) as c:
        yield c


def test_docs_need_no_internet(client):
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "POST /loops" in page.text and "openapi.json" in page.text
    assert not re.search(r"(src|href)=['\"]?(https?:)?//", page.text)  # no external asset
    assert "<script" not in page.text
    assert client.get("/redoc").status_code == 404  # ReDoc loads from a CDN: off
    assert client.get("/openapi.json").json()["paths"]["/loops"]


@pytest.mark.parametrize("path", ["/loops", "/loops/L1/history"])
@pytest.mark.parametrize(
    "query",
    [
        "offset=100000000000000000000",
        "offset=9223372036854775808",
        "offset=9223372036854775807",
        f"offset={MAX_OFFSET + 1}",
        "offset=-1",
        "limit=100000000000000000000",
        "limit=0",
        "offset=1e3",
    ],
)
def test_huge_pagination_values_are_4xx_never_5xx(client, path, query):
    client.post("/loops", json=loop_body("L1"))
    r = client.get(f"{path}?{query}")
    assert r.status_code == 422, r.text


@pytest.mark.parametrize("path", ["/loops", "/loops/L1/history"])
def test_the_largest_offset_is_an_empty_page(client, path):
    client.post("/loops", json=loop_body("L1"))
    r = client.get(f"{path}?offset={MAX_OFFSET}")
    assert r.status_code == 200 and r.json()["items"] == [], r.text


def test_metrics_have_process_metrics_and_no_created_series(client):
    client.post("/loops", json=loop_body("L1"))
    text = client.get("/metrics").text
    for name in (
        "process_cpu_seconds_total",
        "process_resident_memory_bytes",
        "process_open_fds",
        "process_max_fds",
        "python_gc_collections_total",
        "python_info",
        "pitune_samples_received_total",
    ):
        assert re.search(rf"^{name}(\{{| )", text, re.M), name
    assert "_created" not in text


def test_json_log_lines(root_logger):
    stream = io.StringIO()
    logs.configure("INFO", "json", stream)
    logging.getLogger("pitune.test").info("hello %s", "world")
    logging.getLogger("uvicorn.error").info("Application startup complete.")
    try:
        raise ValueError("boom")
    except ValueError:
        logging.getLogger("pitune.test").exception("failed")
    logging.getLogger("pitune.test").debug("not shown")
    lines = stream.getvalue().splitlines()
    entries = [json.loads(line) for line in lines]
    assert [(e["level"], e["logger"], e["message"]) for e in entries] == [
        ("INFO", "pitune.test", "hello world"),
        ("INFO", "uvicorn.error", "Application startup complete."),
        ("ERROR", "pitune.test", "failed"),
    ]
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", entries[0]["ts"])
    assert "ValueError: boom" in entries[2]["exc"]


def test_text_log_lines_have_timestamp_level_logger(root_logger):
    stream = io.StringIO()
    logs.configure("info", "text", stream)
    logging.getLogger("uvicorn.access").info('%s - "%s %s"', "127.0.0.1", "GET", "/x")
    line = stream.getvalue().strip()
    assert re.fullmatch(
        r'\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z INFO uvicorn\.access: 127\.0\.0\.1 - "GET /x"',
        line,
    ), line


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_event_lines_per_change_rate_limited(caplog):
    clock = Clock()
    events = logs.EventLog(logging.getLogger("pitune.events"), burst=3, interval_s=10.0)
    events.limiter.clock = clock
    messages = [
        {"loop_id": f"L{i}", "seq": 1, "t": 5.0, "kp": 1.5, "ki": 0.15, "dkp": 0.5, "dki": 0.05,
         "mode": "auto", "reason": "agent"}
        for i in range(10)
    ]  # fmt: skip
    adopted = audit_row("L0", 0.0, 6.0, 1, "auto", "adopted", (1.5, 0.15), (2.0, 0.2))
    with caplog.at_level(logging.INFO, "pitune.events"):
        events.published(messages)
        events.audit([adopted])
        messages = [r.getMessage() for r in caplog.records]
        assert len(messages) == 4  # 3 agent lines, then the adoption (its own kind)
        assert messages[0] == (
            "loop 'L0' gains kp=1 ki=0.1 -> kp=1.5 ki=0.15 (agent, auto, seq 1) at t=5"
        )
        assert "adopted the gateway's gains kp=2 ki=0.2" in messages[3]
        caplog.clear()
        clock.now = 10.0
        events.flush()  # the burst is over: its count, once
        events.flush()
        assert [r.getMessage() for r in caplog.records] == [
            "7 more agent events not logged in 10 s"
        ]


def test_status_changes_are_logged_once(caplog):
    """Slot by slot: a loop's change is logged once; a new slot, or a slot freed and
    taken by another loop, is a first sight (its registration is logged)."""
    watch = logs.StatusWatch(logs.EventLog())
    code = {status.value: k for k, status in enumerate(STATUSES)}

    def check(*slots):
        ids = [None if s is None else s[0] for s in slots]
        codes = np.array([code["waiting"] if s is None else code[s[1]] for s in slots])
        return watch.check(ids, codes)

    with caplog.at_level(logging.INFO, "pitune.events"):
        assert check(("A", "waiting"), ("B", "tuning")) == []  # first sight
        assert check(("A", "tuning"), ("B", "tuning"), ("C", "waiting")) == [
            ("A", "waiting", "tuning")
        ]
        assert check(("A", "stale"), None, ("C", "waiting")) == [("A", "tuning", "stale")]
        assert check(("A", "stale"), ("D", "tuning"), ("C", "quiet")) == [("C", "waiting", "quiet")]
    assert [r.getMessage() for r in caplog.records] == [
        "loop 'A' status waiting -> tuning",
        "loop 'A' status tuning -> stale",
        "loop 'C' status waiting -> quiet",
    ]


def test_the_status_check_reads_every_slot_of_a_real_table(caplog):
    """What the API's watcher runs: the statuses of a table's slots, a loop's change
    logged once, a deleted one and its slot's next loop not a change."""
    engine = TuningEngine(load_agent())
    engine.register(LoopConfig(id="A", kp=0.5, ki=0.01, sample_period_s=1.0), wall=0.0)
    engine.register(LoopConfig(id="B", kp=0.5, ki=0.01, sample_period_s=1.0), wall=0.0)
    watch = logs.StatusWatch(logs.EventLog())
    with caplog.at_level(logging.INFO, "pitune.events"):
        assert watch.check(*logs.table_statuses(engine.table, 0.0)) == []
        engine.ingest([{"loop_id": "A", "t": 0.0, "sp": 1.0, "pv": 0.0}], wall=0.0)
        engine.remove("B")
        engine.register(LoopConfig(id="C", kp=0.5, ki=0.01, sample_period_s=1.0), wall=0.0)
        changes = watch.check(*logs.table_statuses(engine.table, 0.0))
    assert [c[0] for c in changes] == ["A"] and changes[0][1] == "waiting"
    assert changes[0][2] != "waiting"


def test_rejection_bursts_end_with_their_count(caplog):
    metrics = Metrics()
    metrics._rejections.interval_s = 0.0  # every interval is over at once
    from service.wire.protocol import RejectReason

    with caplog.at_level(logging.WARNING, "pitune.tuner"):
        metrics._rejections.interval_s = 3600.0
        for _ in range(5):
            metrics.reject(RejectReason.out_of_order, "L1", "older")
        metrics._rejections.interval_s = 0.0
        metrics.flush_logs()
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2 and "sample rejected" in messages[0]
    assert messages[1].startswith("4 more out_of_order messages suppressed")


def test_admin_changes_are_logged_at_info(client, caplog):
    with caplog.at_level(logging.INFO, "pitune.events"):
        client.post("/loops", json=loop_body("L1"))
        client.post("/loops/bulk", json=[loop_body(f"B{i}") for i in range(7)])
        client.patch("/loops/L1", json={"mode": "advisory"})
        client.post("/loops/L1/reset")
        client.delete("/loops/L1")
    messages = [r.getMessage() for r in caplog.records]
    assert messages[0].startswith("loop 'L1' registered (auto, kp=0.5 ki=0.01, seq 0) via the API")
    assert messages[1].startswith("7 loops registered in bulk: 'B0', 'B1', 'B2', 'B3', 'B4', ...")
    assert "config changed" in messages[2] and "advisory" in messages[2]
    assert messages[3].startswith("loop 'L1' reset") and messages[4].startswith("loop 'L1' deleted")


def test_the_daemon_writes_json_lines_only(tmp_path):
    """pitune's and uvicorn's lines, start to SIGTERM, each one JSON object."""
    tuner = TunerProcess(tmp_path / "pitune.db", "--agent-weights", "untrained",
                         "--log-format", "JSON", log=tmp_path / "tuner.log",
                         env={"PITUNE_LOG_LEVEL": "INFO"})  # fmt: skip
    try:
        proc = tuner.start()
        with tuner.http() as api:
            assert api.post("/loops", json=loop_body("L1")).status_code == 201
        assert proc.signal(signal.SIGTERM) == 0
    finally:
        tuner.stop()
    entries = [json.loads(line) for line in tuner.log.read_text().splitlines()]
    loggers = {e["logger"] for e in entries}
    assert {"pitune.tuner", "pitune.events", "uvicorn.error", "uvicorn.access"} <= loggers
    assert any("registered" in e["message"] for e in entries if e["logger"] == "pitune.events")


def test_gain_changes_and_adoptions_reach_the_log(tmp_path, caplog):
    """Needs ``Tuner._commit`` to hand the committed audit rows to
    ``self.metrics.events.audit`` (service/daemon/tuner.py, not this module's owner)."""
    import inspect

    from service.daemon.tuner import Tuner
    from service.engine.config import LoopConfig
    from tests.tuner_support import connected_gateway

    if "events.audit" not in inspect.getsource(Tuner._commit):
        pytest.xfail("Tuner._commit does not call metrics.events.audit yet")

    def logged(text: str) -> bool:
        return any(text in r.getMessage() for r in caplog.records)

    with caplog.at_level(logging.INFO, "pitune.events"), Tuner(tuner_settings(tmp_path)) as t:
        t.register(LoopConfig(**loop_body("AUTO")))
        t.register(LoopConfig(**loop_body("SHADOW", mode="shadow")))
        gw = connected_gateway(t.settings)
        try:
            for i in range(170):
                for loop_id in ("AUTO", "SHADOW"):
                    gw.send(loop_id, {"t": float(i), "e": 1.0})
            gw.next_gains()
            wait_until(lambda: t.view("SHADOW").counters.steps >= 1)
            for loop_id in ("AUTO", "SHADOW"):  # an operator's change, committed after
                gw.send(loop_id, {"t": 170.0, "e": 1.0, "kp": 0.9, "ki": 0.02})
            wait_until(lambda: logged("'AUTO' adopted") and logged("'SHADOW' adopted"))
        finally:
            gw.close()
    messages = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("loop 'AUTO' gains kp=0.5 ki=0.01 -> ") for m in messages)
    assert any("adopted the gateway's gains kp=0.9 ki=0.02" in m for m in messages)
    # a shadow loop's steps publish nothing: no gains line (each wrote one)
    assert not any(m.startswith("loop 'SHADOW' gains") for m in messages), messages


@pytest.mark.parametrize("level", ["info", "debug"])
def test_probes_and_scrapes_stay_out_of_the_access_log_at_info(tmp_path, level):
    """A liveness probe every 2 s wrote 43,200 access lines a day: /healthz, /readyz and
    /metrics answered are DEBUG lines (shown at --log-level debug only); any other
    request, and a probe refused (HEAD on /healthz: 405), stays an INFO line."""
    tuner = TunerProcess(tmp_path / "pitune.db", "--agent-weights", "untrained",
                         "--log-format", "json", "--log-level", level,
                         log=tmp_path / "tuner.log")  # fmt: skip
    try:
        tuner.start()
        with tuner.http() as api:
            for _ in range(3):
                for path in ("/healthz", "/readyz", "/metrics", "/metrics?name[]=x"):
                    assert api.get(path).status_code == 200, path
            assert api.get("/loops").status_code == 200
            assert api.head("/healthz").status_code == 405
            assert api.get("/nope").status_code == 404
    finally:
        tuner.stop()
    entries = [json.loads(line) for line in tuner.log.read_text().splitlines()]
    access = [(e["level"], e["message"].split(" - ", 1)[1]) for e in entries
              if e["logger"] == "uvicorn.access"]  # fmt: skip
    shown = [line for line in access if line[0] == "INFO"]
    assert shown == [
        ("INFO", '"GET /loops HTTP/1.1" 200'),
        ("INFO", '"HEAD /healthz HTTP/1.1" 405'),
        ("INFO", '"GET /nope HTTP/1.1" 404'),
    ]
    probes = [message for lvl, message in access if lvl == "DEBUG"]
    if level == "info":
        assert probes == []
    else:  # the 12 above and the start-up's readiness polls
        assert len(probes) >= 12
        assert all(
            re.fullmatch(r'"GET /(healthz|readyz|metrics)\S* HTTP/1.1" 200', m) for m in probes
        )
