"""The vectorised batch path (``LoopTable.ingest_many``, ``_batch_columns``) equals the
one-sample-at-a-time path in every state change, due step, rejection and audit row."""

from __future__ import annotations

import numpy as np
import orjson
import pytest

from service.agent import untrained_agent
from service.daemon.tuner import _batch_columns
from service.engine.config import LoopConfig
from service.engine.table import _BOOL, _F64, _I64, LoopTable, Rejected
from service.wire.protocol import Mode, Sample
from tests.tuner_support import loop_body

N = 12


def _tables(rate: float) -> tuple[LoopTable, LoopTable]:
    tables = []
    for _ in range(2):
        t = LoopTable(untrained_agent(0), max_rate_hz=rate, capacity=4)
        for i in range(N):
            mode = [Mode.auto, Mode.advisory, Mode.frozen][i % 3]
            scaling = {"k_hat": 1.2, "tau_hat": 1.0 + i % 4, "pv_scale": 10.0}  # RL every 5.5..22 s
            gate = {"excitation_periods": 3.0 * (i % 2)}  # the excitation gate on odd loops
            body = loop_body(f"L{i}", sample_period_s=1.0, mode=mode, scaling=scaling, guard=gate)
            t.add(LoopConfig(**body), wall=0.0)
        tables.append(t)
    return tables[0], tables[1]


def _random_batch(rng, table: LoopTable, k: float) -> list[dict]:
    """One sample for a random subset of the loops, with every kind of oddity."""
    items = []
    for i in rng.permutation(N)[: rng.integers(1, N + 1)]:
        s = table.slot_of[f"L{i}"]
        last = table.last_t[s]
        roll = rng.random()
        if np.isnan(last) or roll > 0.15:
            gap = 8.0 if rng.random() < 0.05 else 0.0  # sometimes a stale gap
            t = max(k, float(last) + 1.0 if not np.isnan(last) else k) + gap
        elif roll > 0.08:
            t = float(last)  # duplicate
        else:
            t = float(last) - 1.0  # out of order
        item = {"loop_id": f"L{i}", "t": t}
        if rng.random() < 0.5:
            item["e"] = float(rng.choice([rng.normal(0, 2.0), 5000.0]) if rng.random() < 0.05
                              else rng.normal(0, 2.0))  # fmt: skip
        else:
            # setpoint steps above and below the gate's smallest (2.0 here), and none
            item["sp"] = float(rng.choice([1.0, 1.0, 1.0, 2.5, 4.0]))
            item["pv"] = float(rng.normal(1.0, 2.0))
        if rng.random() < 0.4:  # report gains: current, previous (in flight) or new
            choice = rng.integers(3)
            kp = [table.kp[s], table.prev_kp[s] or 0.3, float(rng.uniform(0.1, 1.0))][choice]
            item["kp"] = float(kp)
            if rng.random() < 0.7:
                item["ki"] = float([table.ki[s], table.prev_ki[s] or 0.02, 0.05][choice])
        if rng.random() < 0.1:
            item["auto"] = False
        if rng.random() < 0.1:
            item["saturated"] = True
        items.append(item)
    return items


def _slow(table: LoopTable, items: list[dict], wall: float):
    due, rejected = [], []
    for item in items:
        s = table.slot_of[item["loop_id"]]
        try:
            if table.ingest(s, Sample.model_validate(item), wall):
                due.append(s)
        except Rejected as exc:
            rejected.append((item["loop_id"], exc.reason, exc.detail))
    return due, rejected


def _fast(table: LoopTable, items: list[dict], wall: float):
    slots, cols = _batch_columns(items, table.slot_of)
    mask, rejections = table.ingest_many(slots, cols, wall)
    rejected = [(items[i]["loop_id"], reason, detail) for i, reason, detail in rejections]
    return slots[mask].tolist(), rejected


def _plain(changes) -> str:
    """Changes as text, so that NaN equals NaN and np.float64 equals float."""
    gains, audit = changes
    return repr([[v if isinstance(v, str) else float(v) for v in row] for row in gains]) + repr(
        [[v if isinstance(v, str) or v is None else float(v) for v in row] for row in audit]
    )


@pytest.mark.parametrize(("seed", "rate"), [(0, 1e6), (1, 1e6), (2, 1.5)])
def test_ingest_many_equals_ingest_one_by_one(seed, rate):
    rng = np.random.default_rng(seed)
    slow, fast = _tables(rate)
    for k in range(60):
        wall = 100.0 + 0.5 * k
        items = _random_batch(rng, slow, 10.0 + 2.0 * k)
        assert _slow(slow, items, wall) == _fast(fast, items, wall), k
        for name in (*_F64, *_I64, *_BOOL):
            np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        assert _plain(fast.drain_changes()) == _plain(slow.drain_changes())
        due = np.array([s for s in range(N) if rng.random() < 0.3], dtype=np.int64)
        if due.size:  # steps change gains and put updates in flight
            slow.step(due, wall)
            fast.step(due, wall)
            np.testing.assert_array_equal(fast.hidden, slow.hidden)


@pytest.mark.parametrize(
    "items",
    [
        [{"loop_id": "L0", "t": 1, "e": 0.0}],  # an int: pydantic decides
        [{"loop_id": "L0", "t": 1.0, "e": 0.0, "auto": None}],  # explicit null flag
        [{"loop_id": "L0", "t": 1.0, "e": 0.0, "v": 2}],
        [{"loop_id": "L0", "t": 1.0, "e": 0.0, "v": True}],
        [{"loop_id": "L0", "t": 1.0, "sp": 1.0}],  # no pv
        [{"loop_id": "L0", "t": 1.0, "e": 0.0, "kp": -1.0}],
        [{"loop_id": "L0", "t": 1.0, "e": 2e12}],
        [{"loop_id": "nope", "t": 1.0, "e": 0.0}],
        [{"loop_id": "L0", "t": 1.0, "e": 0.0}, {"loop_id": "L0", "t": 2.0, "e": 0.0}],
        [{"loop_id": "L0", "t": "1.0", "e": 0.0}],
        ["not an object"],
        [],
    ],
)
def test_anything_unusual_takes_the_exact_slow_path(items):
    table, _ = _tables(1e6)
    assert _batch_columns(items, table.slot_of) is None


def test_plain_batch_is_columnar():
    table, _ = _tables(1e6)
    items = [
        {"loop_id": "L1", "t": 5.0, "sp": 2.0, "pv": 0.5, "kp": 0.5, "extra": "ignored"},
        {"loop_id": "L2", "t": 6.0, "e": -1.0, "saturated": True, "auto": False, "v": 1},
    ]
    slots, cols = _batch_columns(items, table.slot_of)
    assert slots.tolist() == [table.slot_of["L1"], table.slot_of["L2"]]
    np.testing.assert_array_equal(cols["e"], [1.5, -1.0])
    assert np.isnan(cols["ki"]).all() and cols["kp"][0] == 0.5 and np.isnan(cols["kp"][1])
    assert cols["auto"].tolist() == [True, False]
    assert cols["saturated"].tolist() == [False, True]


def test_single_sample_messages_received_together_are_ingested_as_one_batch(tmp_path):
    from service.daemon.bus import Kind
    from service.daemon.tuner import Tuner
    from tests.tuner_support import tuner_settings

    with Tuner(tuner_settings(tmp_path)) as tuner:
        for i in range(3):
            tuner.register(LoopConfig(**loop_body(f"L{i}")))
        keys, slow_calls = tuner.keys, []
        original = tuner._on_sample
        tuner._on_sample = lambda *a: (slow_calls.append(a[0]), original(*a))[1]

        def single(loop_id, body):
            return (Kind.sample, keys.sample(loop_id), orjson.dumps(body))

        tuner._handle([single(f"L{i}", {"t": 1.0, "e": 0.5, "loop_id": "x"}) for i in range(3)])
        assert slow_calls == []  # one vectorised pass; the key names the loop
        # an int timestamp and a loop twice: one by one, with exact rejections
        tuner._handle(
            [
                single("L0", {"t": 2, "e": 0.5}),
                single("L1", {"t": 2.0, "e": 0.5}),
                single("L1", {"t": 2.0, "e": 0.5}),
            ]
        )
        assert len(slow_calls) == 3
        table = tuner.table
        assert [int(table.n_samples[table.slot_of[f"L{i}"]]) for i in range(3)] == [2, 2, 1]
        assert tuner.metrics.value("pitune_samples_received_total") == 6
        assert tuner.metrics.value("pitune_samples_rejected_total", reason="duplicate") == 1
