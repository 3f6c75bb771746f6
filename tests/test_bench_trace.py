"""``pitune bench --instances N --trace FILE``: the generators' latencies carry the
publish time of their sample and its loop, so a tail can be placed in the window."""

from __future__ import annotations

import csv

import orjson

from service.bench.gateways import Plan, _Latencies
from service.bench.load import write_trace


def test_the_generators_latencies_keep_publish_time_and_loop_for_the_trace(tmp_path):
    plan = Plan(
        gateways={"gw": ["A", "B"]}, endpoints=[], period=1.0, groups=2, batch_size=10,
        columns=True, window=(0.0, 10.0), end=10.0, t0=1000.0,
    )  # fmt: skip
    lat = _Latencies(plan)
    lo, hi = 100.0, 110.0
    lat.stamp(0, 3, 102.0)  # group 0 (loop A), 4th sample, published at 102 s
    lat.stamp(1, 3, 102.5)  # group 1 (loop B): plant time 1003.5
    lat.stamp(0, 20, 99.0)  # before the window: not counted
    gains = [
        {"loop_id": "A", "t": 1003.0, "seq": 1},
        {"loop_id": "B", "t": 1003.5, "seq": 1},
        {"loop_id": "A", "t": 1020.0, "seq": 2},
        {"loop_id": "B", "t": 1003.5, "seq": 2, "reason": "reset"},
    ]
    lat.inbox.append((102.04, orjson.dumps({"gains": gains[:1]})))
    lat.inbox.append((102.6, orjson.dumps({"gains": gains[1:]})))
    lat.drain(lo, hi)
    assert lat.gains == 4 and lat.unmatched == 0
    assert [round(v, 3) for v in lat.values] == [0.04, 0.1]  # not the reset, not before
    assert lat.trace == [(2.0, "A"), (2.5, "B")]  # publish time in the window, loop
    path = tmp_path / "trace.csv"
    write_trace(path, [(t, i, d) for (t, i), d in zip(lat.trace, lat.values, strict=True)])
    with open(path) as f:
        rows = list(csv.DictReader(f))
    assert [r["loop_id"] for r in rows] == [i for _, i in lat.trace]
    assert float(rows[0]["t_s"]) == 2.0 and float(rows[0]["latency_ms"]) == 40.0
