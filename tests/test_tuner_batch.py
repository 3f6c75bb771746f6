"""The engine's one vectorised ingest path (``wire.decode`` + ``LoopTable.ingest``) equals
the scalar reference (tests/engine_reference.py) in every state change, due step,
rejection and audit row; the decoder agrees with the pydantic models on any input."""

from __future__ import annotations

import numpy as np
import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from service.agent import untrained_agent
from service.daemon.delivery import _within_size
from service.engine import op_law, output_limit, rules
from service.engine.config import LoopConfig
from service.engine.plant_hold import RELEASED, PlantHold
from service.engine.stepping import step
from service.engine.table import _BOOL, _F64, _I64, _REC, LoopTable
from service.wire.decode import classify, decode_batch, decode_columns, decode_objects, joined
from service.wire.protocol import (
    MAX_BATCH,
    MAX_MESSAGE_BYTES,
    BatchedSample,
    GainsMessage,
    Mode,
    RejectReason,
    Sample,
)
from tests.engine_reference import Rejected, reference_ingest
from tests.tuner_support import loop_body

HELD = PlantHold(held=True, since=0.0, by="api", reason="a test")
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
            if i % 4 == 3:  # registered without a hint: identifying
                body["scaling"] = None
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
            # setpoint steps above and below the gate's smallest (2.0 here), none, and runs
            # of moves in one direction (a ramp's or a staircase's)
            item["sp"] = float(rng.choice([1.0, 1.0, 1.0, 2.5, 4.0, 6.5, 9.0]))
            item["pv"] = float(rng.normal(1.0, 2.0))
        if rng.random() < 0.4:  # report gains: current, previous (in flight) or new
            choice = rng.integers(3)
            kp = [table.kp[s], table.prev_kp[s] or 0.3, float(rng.uniform(0.1, 1.0))][choice]
            item["kp"] = float(kp)
            if rng.random() < 0.7:
                item["ki"] = float([table.ki[s], table.prev_ki[s] or 0.02, 0.05][choice])
            if rng.random() < 0.5:  # the update the DCS applied: behind, current, ahead
                item["applied_seq"] = max(0, int(table.seq[s]) + int(rng.integers(-2, 2)))
        if i % 3 == 1:  # an output that mostly stays where it is (held at a limit), or not
            item["op"] = 1.5 if rng.random() < 0.85 else float(rng.normal(1.0, 0.3))
        elif i % 3 == 2 and rng.random() < 0.5:
            item["op"] = float(rng.normal(1.0, 0.3))
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
            if reference_ingest(table, s, Sample.model_validate(item), wall):
                due.append(s)
        except Rejected as exc:
            rejected.append((item["loop_id"], exc.reason, exc.detail))
    return due, rejected


def _fast(table: LoopTable, items: list[dict], wall: float):
    decoded = decode_objects(items)
    assert not decoded.rejected
    slots = np.array([table.slot_of[i] for i in decoded.rows.loop_ids], np.int64)
    mask, rejections = rules.ingest(table, slots, decoded.rows, wall)
    table.n_rejected[slots[[i for i, _, _ in rejections]]] += 1  # as the engine counts them
    rejected = [(items[i]["loop_id"], reason, detail) for i, reason, detail in rejections]
    return slots[mask].tolist(), rejected


def _plain(changes) -> str:
    """Changes as text, so that NaN equals NaN and np.float64 equals float; audit rows in
    each loop's order (the vectorised rules take a batch rule by rule, the reference
    sample by sample: rows of different loops may interleave differently)."""
    gains, audit = changes
    audit = sorted(audit, key=lambda row: row[0])
    return repr([[v if isinstance(v, str) else float(v) for v in row] for row in gains]) + repr(
        [[v if isinstance(v, str) or v is None else float(v) for v in row] for row in audit]
    )


@pytest.mark.parametrize(("seed", "rate"), [(0, 1e6), (1, 1e6), (2, 1.5)])
def test_vectorised_ingest_equals_the_scalar_reference(seed, rate, monkeypatch):
    # held outputs after 3 samples instead of 20: the random runs are short
    monkeypatch.setattr(output_limit, "HELD_SAMPLES", 3)
    rng = np.random.default_rng(seed)
    holds = 0
    slow, fast = _tables(rate)
    for k in range(60):
        wall = 100.0 + 0.5 * k
        # the plant-wide hold for a while: no loop due, none counted quiet
        slow.hold = fast.hold = HELD if 20 <= k < 30 else RELEASED
        items = _random_batch(rng, slow, 10.0 + 2.0 * k)
        due, rejected = _slow(slow, items, wall)
        assert (due, rejected) == _fast(fast, items, wall), k
        assert not due or slow.hold is RELEASED, k
        for name in (*_F64, *_I64, *_REC, *_BOOL, *output_limit.F64, *output_limit.BOOL,
                     *op_law.F64):  # fmt: skip
            np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        holds += int(fast.oh_held.sum())
        for s in range(N):  # identification: recorded data, events, models
            rec = fast.rec[s]
            if rec >= 0:
                n = fast.rec_n[s]
                np.testing.assert_array_equal(
                    fast.recorder.data[rec, :, :n], slow.recorder.data[slow.rec[s], :, :n]
                )
            assert fast.ident[s].dump() == slow.ident[s].dump()
        assert _plain(fast.drain_changes()) == _plain(slow.drain_changes())
        due = np.array([s for s in range(N) if rng.random() < 0.3], dtype=np.int64)
        if due.size:  # steps change gains and put updates in flight
            step(slow, due, wall)
            step(fast, due, wall)
            np.testing.assert_array_equal(fast.hidden, slow.hidden)
    assert holds and fast.n_held.sum() >= 2  # the rule was exercised, onsets audited
    assert np.isfinite(fast.ramp_t[: len(fast.ids)]).any()  # and so was the ramp rule


_value = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 3), st.text(max_size=3),
    st.floats(allow_nan=False, allow_infinity=False, min_value=-2e12, max_value=2e12),
    st.sampled_from([0.0, -1.0, 1.0, 0.5, 1e12, 2e12]),
)  # fmt: skip
_KEYS = ("loop_id", "t", "e", "sp", "pv", "kp", "ki", "auto", "saturated", "v", "extra",
         "applied_seq")  # fmt: skip
_item = st.one_of(
    st.dictionaries(
        st.sampled_from(_KEYS),
        st.one_of(_value, st.sampled_from(["L0", "L1", "bad/id", "", 7, 2**63, 2**70])),
        max_size=9,
    ),
    _value,
    st.lists(_value, max_size=2),
)


_uniform = st.integers(0, 5).flatmap(
    lambda n: st.lists(st.fixed_dictionaries({"loop_id": st.sampled_from(["L0", "L1", "bad/id"]),
                                              "t": _value, "e": _value}), min_size=n, max_size=n)
)  # fmt: skip
"""A gateway's batch: every sample with the same fields (the decoder's one-pass case)."""


@settings(max_examples=400, deadline=None)
@given(st.one_of(st.lists(_item, max_size=6), _uniform))
def test_the_decoder_agrees_with_the_pydantic_models(items):
    """Every item is accepted with the model's values, or rejected with the model's
    reason; accepted + rejected = received; order is kept."""
    decoded = decode_objects(items)
    assert decoded.received == len(items)
    assert len(decoded.rows) + len(decoded.rejected) == len(items)
    accepted = dict(zip(decoded.rows.index.tolist(), range(len(decoded.rows)), strict=True))
    rejected = {r.index: r for r in decoded.rejected}
    for i, item in enumerate(items):
        try:
            model = BatchedSample.model_validate(item)
        except ValidationError as exc:
            assert rejected[i].reason is classify(exc)
            continue
        row = accepted[i]
        assert decoded.rows.loop_ids[row] == model.loop_id
        assert decoded.rows.t[row] == model.t and decoded.rows.e[row] == model.error
        for name in ("sp", "kp", "ki"):
            value = getattr(model, name)
            got = getattr(decoded.rows, name)[row]
            assert (np.isnan(got) and value is None) or got == value
        assert decoded.rows.auto[row] == model.auto
        assert decoded.rows.saturated[row] == model.saturated
        seq = -1 if model.applied_seq is None else min(model.applied_seq, 2**63 - 1)
        assert decoded.rows.applied_seq[row] == seq
    assert decoded.rows.index.tolist() == sorted(accepted)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.lists(_item, max_size=4), _uniform), min_size=1, max_size=4))
def test_batches_joined_decode_as_their_samples_together(parts):
    """Batch messages the worker handles in one pass (a backlog) are what their samples
    received together decode to: the same rows, positions and rejections."""
    whole = decode_objects([item for part in parts for item in part])
    one = joined([decode_objects(part) for part in parts])
    assert one.received == whole.received
    assert one.rows.loop_ids == whole.rows.loop_ids
    for name in ("t", "e", "sp", "kp", "ki", "auto", "saturated", "index", "op", "applied_seq"):
        np.testing.assert_array_equal(getattr(one.rows, name), getattr(whole.rows, name))

    def seen(d):
        return [(r.index, r.loop_id, r.reason) for r in d.rejected]

    assert seen(one) == seen(whole)


_columns = st.tuples(
    st.lists(st.sampled_from(_KEYS), unique=True, min_size=1, max_size=7),
    st.integers(0, 5),
).flatmap(
    lambda kn: st.lists(
        st.fixed_dictionaries(
            {k: st.one_of(_value, st.sampled_from(["L0", "L1", "bad/id"])) if k == "loop_id"
             else _value for k in kn[0]}
        ),
        min_size=kn[1], max_size=kn[1],
    ).map(lambda rows, keys=kn[0]: (keys, rows))
)  # fmt: skip
"""A columns message's samples: every sample with the same fields (any values)."""


def _same(a, b):
    assert a.received == b.received and a.rows.loop_ids == b.rows.loop_ids
    for name in ("t", "e", "sp", "kp", "ki", "auto", "saturated", "index", "op", "applied_seq"):
        np.testing.assert_array_equal(getattr(a.rows, name), getattr(b.rows, name), name)
    assert [(r.index, r.loop_id, r.reason) for r in a.rejected] == [
        (r.index, r.loop_id, r.reason) for r in b.rejected
    ]


@settings(max_examples=400, deadline=None)
@given(_columns)
def test_columns_decode_as_the_batch_of_their_rows(case):
    """A columns message is its rows' batch: the same rows accepted, the same values,
    positions and rejections (the rows' decoder agrees with the models, above)."""
    keys, rows = case
    message = {"v": 1, "columns": {k: [row[k] for row in rows] for k in keys}}
    _same(decode_columns(message), decode_objects(rows))
    _same(decode_batch(orjson.dumps(message)), decode_objects(rows))


def test_a_gateways_columns_are_taken_whole_and_bad_shapes_rejected_whole():
    columns = {
        "loop_id": ["L0", "L1", "L2"],
        "t": [1.0, 1.0, 1.0],
        "sp": [2.0, 2.0, None],
        "pv": [1.5, 0.5, 1.0],
        "e": [None, None, 0.25],
        "op": [10.0, 20.0, 30.0],
    }
    rows = decode_batch(orjson.dumps({"v": 1, "columns": columns})).rows
    assert rows.loop_ids == ["L0", "L1", "L2"]
    np.testing.assert_array_equal(rows.e, [0.5, 1.5, 0.25])
    np.testing.assert_array_equal(rows.op, [10.0, 20.0, 30.0])
    assert rows.auto.all() and np.isnan(rows.kp).all() and (rows.applied_seq == -1).all()
    odd = {**columns, "t": [1.0, 2, 1.0]}  # an int: judged by the model (accepted as 2.0)
    assert decode_batch(orjson.dumps({"columns": odd})).rows.t.tolist() == [1.0, 2.0, 1.0]
    for message, n, detail in [
        ({"columns": {**columns, "t": [1.0]}}, 3, "unequal lengths [1, 3]"),
        ({"columns": [columns]}, 1, "not an object of lists"),
        ({"columns": {"loop_id": "L0", "t": 1.0}}, 1, "not an object of lists"),
        ({"columns": {"loop_id": ["L0"] * (MAX_BATCH + 1)}}, MAX_BATCH + 1, "at most"),
        # both forms: the columns were taken and the samples counted nowhere (review 40)
        ({"columns": columns, "samples": [{"loop_id": "L9", "t": 1.0, "e": 0.1}]}, 4, "both"),
    ]:
        bad = decode_batch(orjson.dumps(message))
        # rejected whole: one rejection standing for every sample
        assert len(bad.rows) == 0 and len(bad.rejected) == 1
        assert bad.received == bad.rejected[0].count == n
        assert {r.reason for r in bad.rejected} == {RejectReason.schema}
        assert detail in bad.rejected[0].detail
    newer = decode_batch(orjson.dumps({"v": 2, "columns": columns}))
    assert {r.reason for r in newer.rejected} == {RejectReason.unsupported_version}
    nan = b'{"columns":{"loop_id":["L0","L1"],"t":[1.0,1.0],"e":[NaN,0.5]}}'
    lax = decode_batch(nan)
    assert lax.rows.loop_ids == ["L1"] and lax.rejected[0].reason is RejectReason.non_finite


def test_one_bad_sample_does_not_take_its_batch_with_it():
    """NaN as Python's json writes it rejects that sample only, every sample is counted,
    and a batch over the documented limit is rejected whole, each sample counted."""
    good = [{"loop_id": f"L{i}", "t": 1.0, "e": 0.5} for i in range(3)]
    payload = orjson.dumps({"samples": good})[:-2] + b',{"loop_id":"L9","t":1.0,"e":NaN}]}'
    decoded = decode_batch(payload)
    assert decoded.rows.loop_ids == ["L0", "L1", "L2"] and decoded.received == 4
    assert [(r.index, r.loop_id, r.reason) for r in decoded.rejected] == [
        (3, "L9", RejectReason.non_finite)
    ]
    big = decode_batch(orjson.dumps({"samples": [good[0]] * (MAX_BATCH + 1)}))
    assert len(big.rows) == 0 and len(big.rejected) == 1
    assert big.received == big.rejected[0].count == MAX_BATCH + 1
    assert {r.reason for r in big.rejected} == {RejectReason.schema}


def test_reject_reasons_of_a_negative_applied_seq_and_of_v_below_1_are_the_documented():
    """docs/protocol.md, Accounting: an applied_seq below 0 is out_of_range, a v below 1
    unsupported_version, in a sample and on a batch (an integrator met both undocumented)."""
    sample = {"loop_id": "L0", "t": 1.0, "e": 0.5}
    for extra, reason in [
        ({"applied_seq": -1}, RejectReason.out_of_range),
        ({"v": 0}, RejectReason.unsupported_version),
        ({"v": 2}, RejectReason.unsupported_version),
    ]:
        decoded = decode_batch(orjson.dumps({"samples": [sample, {**sample, **extra}]}))
        assert decoded.rows.loop_ids == ["L0"] and decoded.received == 2
        assert [(r.index, r.reason) for r in decoded.rejected] == [(1, reason)]
    whole = decode_batch(orjson.dumps({"v": 0, "samples": [sample, sample]}))
    assert [(r.reason, r.count) for r in whole.rejected] == [(RejectReason.unsupported_version, 2)]


def test_plain_batch_is_columnar():
    items = [
        {"loop_id": "L1", "t": 5.0, "sp": 2.0, "pv": 0.5, "kp": 0.5, "extra": "ignored"},
        {"loop_id": "L2", "t": 6.0, "e": -1.0, "saturated": True, "auto": False, "v": 1},
    ]
    rows = decode_objects(items).rows
    assert rows.loop_ids == ["L1", "L2"]
    np.testing.assert_array_equal(rows.e, [1.5, -1.0])
    assert np.isnan(rows.ki).all() and rows.kp[0] == 0.5 and np.isnan(rows.kp[1])
    assert rows.auto.tolist() == [True, False]
    assert rows.saturated.tolist() == [False, True]


def test_single_sample_messages_received_together(tmp_path):
    from service.daemon.bus import Kind
    from service.daemon.tuner import Tuner
    from tests.tuner_support import tuner_settings

    with Tuner(tuner_settings(tmp_path)) as tuner:
        for i in range(3):
            tuner.register(LoopConfig(**loop_body(f"L{i}")))
        keys = tuner.keys

        def single(loop_id, body):
            return (Kind.sample, keys.sample(loop_id), orjson.dumps(body))

        tuner._handle([single(f"L{i}", {"t": 1.0, "e": 0.5, "loop_id": "x"}) for i in range(3)])
        # an int timestamp (the model accepts it) and a loop twice: exact rejections
        tuner._handle(
            [
                single("L0", {"t": 2, "e": 0.5}),
                single("L1", {"t": 2.0, "e": 0.5}),
                single("L1", {"t": 2.0, "e": 0.5}),
            ]
        )
        table = tuner.table
        assert [int(table.n_samples[table.slot_of[f"L{i}"]]) for i in range(3)] == [2, 2, 1]
        assert tuner.metrics.value("pitune_samples_received_total") == 6
        assert tuner.metrics.value("pitune_samples_rejected_total", reason="duplicate") == 1


def test_a_gateways_gains_batch_is_split_to_fit_a_message():
    """100,000 items of long loop ids exceed MAX_MESSAGE_BYTES, which routers and
    gateways drop unread (their links take 33 MiB): the lane splits the batch so each
    message fits, every item once, in order."""
    why = "reason=agent basis=hint dkp=+3.2% dki=+1.1% guard=none verdict=pending"
    item = GainsMessage(loop_id="L" * 64, seq=123456, t=1733333333.123456,
                        dkp=0.012345678901234, dki=0.00012345678901234, kp=1.2345678901234567,
                        ki=0.012345678901234567, mode="auto", instance_id="tuner-a-0123456789",
                        epoch=1733333333123, why=why)  # fmt: skip
    messages = [{**item.model_dump(mode="json"), "seq": k} for k in range(MAX_BATCH)]
    payloads = _within_size(messages)
    assert len(payloads) > 1 and all(len(p) <= MAX_MESSAGE_BYTES for p in payloads)
    seqs = [g["seq"] for p in payloads for g in orjson.loads(p)["gains"]]
    assert seqs == list(range(MAX_BATCH))
