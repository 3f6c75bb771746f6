"""The daemon's ring of recent samples and gains (service/daemon/recent.py)."""

from __future__ import annotations

import numpy as np
import pytest

from service.daemon.recent import REASONS, Recent
from service.engine.updates import StepResult
from service.wire.decode import Columns, Decoded
from service.wire.protocol import UpdateReason


def columns(ids, t, sp=None, e=None, op=None):
    n = len(ids)
    nan = np.full(n, np.nan)
    return Columns(
        list(ids), np.asarray(t, float), np.asarray(e if e is not None else nan, float),
        np.asarray(sp if sp is not None else nan, float), np.full(n, 0.5), np.full(n, 0.01),
        np.ones(n, bool), np.zeros(n, bool), np.arange(n),
        None if op is None else np.asarray(op, float),
    )  # fmt: skip


def step(ids, t, kp, ki, reason=UpdateReason.agent):
    n = len(ids)
    new = np.column_stack([kp, ki]).astype(float)
    return StepResult(
        list(ids), np.asarray(t, float), np.arange(n), np.zeros(n, np.int64), new * 0.9,
        new, new, [None] * n, reason,
    )  # fmt: skip


def test_interleaved_loops_keep_their_own_order_and_pv_is_sp_minus_e():
    r = Recent(known={"A": 0, "B": 1}, points=8)
    r.add_samples(columns(["A", "B", "A", "X", "B", "A"], [1, 1, 2, 2, 2, 3],
                          sp=[10] * 6, e=[1, 2, 3, 4, 5, 6]))  # fmt: skip
    a = r.since("A")
    assert a["t"] == [1.0, 2.0, 3.0] and a["n"] == 3
    assert a["pv"] == [9.0, 7.0, 4.0]
    assert r.since("B")["t"] == [1.0, 2.0]
    assert "X" not in r.slot_of  # not registered: ignored
    assert r.since("X")["n"] == 0


def test_ring_wraps_and_keeps_the_newest_points_also_within_one_batch():
    r = Recent(points=4)
    r.add_samples(Decoded(columns(["A"] * 10, range(10)), [], 10))  # Decoded is accepted
    assert r.since("A")["t"] == [6.0, 7.0, 8.0, 9.0] and r.since("A")["n"] == 10
    r.add_samples(columns(["A", "A"], [10, 11]))
    assert r.since("A")["t"] == [8.0, 9.0, 10.0, 11.0]
    assert r.since("A", samples_seen=10)["t"] == [10.0, 11.0]  # only what is new
    assert r.since("A", samples_seen=12)["t"] == []


def test_unknown_fields_are_none_and_op_is_kept():
    r = Recent(points=4)
    r.add_samples(columns(["A", "A"], [1, 2], op=[30.0, 31.0]))
    got = r.since("A")
    assert got["op"] == [30.0, 31.0] and got["sp"] == [None, None] and got["pv"] == [None, None]


def test_gains_ring_and_summary():
    r = Recent(points=4, gains=3)
    r.add_samples(columns(["A", "B"], [1, 1], sp=[10, 10], e=[3, 4]))
    for k in range(5):
        r.add_gains(step(["A"], [k], [1.0 + k], [0.1]), wall=100.0 + k)
    r.add_gains(step(["B"], [0], [2.0], [0.2], UpdateReason.reset), wall=50.0)
    gains = r.since("A")["gains"]
    assert [g["kp"] for g in gains] == [3.0, 4.0, 5.0] and gains[-1]["reason"] == "agent"
    assert r.since("A", gains_seen=4)["gains"][0]["kp"] == 5.0
    s = r.summary(["A", "B", "C"])
    assert s["last_wall"][0] == 104.0 and s["last_wall"][1] == 50.0 and np.isnan(s["last_wall"][2])
    # each decision's change from the gains it replaced (step(): 0.9 times its own)
    assert s["dkp"][:2] == pytest.approx([1 / 0.9 - 1] * 2) and np.isnan(s["dkp"][2])
    assert s["rms_e"][0] == 3.0 and s["rms_e"][1] == 4.0 and np.isnan(s["rms_e"][2])


def test_every_published_reason_is_shown_by_its_name():
    """An accepted proposal and a model's tuning are named (they showed as 'other')."""
    r = Recent(points=4, gains=len(UpdateReason))
    for k, reason in enumerate(UpdateReason):
        r.add_gains(step(["A"], [k], [1.0], [0.1], reason), wall=100.0 + k)
    assert [g["reason"] for g in r.since("A")["gains"]] == [str(x) for x in UpdateReason]
    assert {"accepted", "model"} <= {str(x) for x in UpdateReason}


def test_size_is_bounded_per_loop_and_forget_frees_the_slot():
    r = Recent(points=256, gains=32, capacity=1)
    ids = [f"L{i}" for i in range(100)]
    for _ in range(3):
        r.add_samples(columns(ids * 10, np.repeat(np.arange(10.0), 100)))
    per_loop = r.nbytes / r._cap
    assert per_loop < 9.5 * 1024  # documented: about 9 KB per loop
    r.forget("L5")
    assert r.since("L5")["n"] == 0
    assert r.retain(set(ids[:50])) == 50  # L50..L99
    r.add_samples(columns(["L1"], [99.0]))
    assert r.since("L1")["t"][-1] == 99.0


def test_a_reused_slot_shows_nothing_of_its_former_loop():
    """A forgotten loop's points are not cleared, only uncounted: the loop that gets its
    slot next shows its own points alone, in its trend and in its rms error."""
    r = Recent(points=4, capacity=1)
    r.add_samples(columns(["A"] * 3, [1.0, 2.0, 3.0], e=[5.0, 5.0, 5.0]))
    r.forget("A")
    r.add_samples(columns(["B"], [9.0], e=[2.0]))
    assert r.slot_of["B"] == 0  # A's slot
    assert r.since("B")["t"] == [9.0]
    assert r.summary(["B"])["rms_e"][0] == 2.0
    assert np.isnan(r.summary(["C"])["rms_e"][0])


def test_table_slots_find_each_loops_own_ring_also_after_a_slot_is_reused():
    from service.engine.config import LoopConfig
    from service.engine.engine import TuningEngine
    from tests.tuner_support import loop_body

    engine = TuningEngine()
    for loop_id in ("A", "B"):
        engine.register(LoopConfig(**loop_body(loop_id)))
    table = engine.table
    r = Recent(points=8, table=table)

    def add(ids, t):
        slots = np.array([table.slot_of.get(i, -1) for i in ids], np.int64)
        r.add_samples(Decoded(columns(ids, t), [], len(ids), slots))

    add(["A", "B", "X"], [1, 1, 1])
    add(["B", "A"], [2, 2])  # through the map now
    assert r.since("A")["t"] == [1.0, 2.0] and r.since("B")["t"] == [1.0, 2.0]
    assert "X" not in r.slot_of  # not registered: ignored, as by id
    engine.remove("A")
    r.forget("A")
    engine.register(LoopConfig(**loop_body("C")))  # takes A's table slot
    add(["C", "B"], [3, 3])  # by id while loops come and go, then a new map
    add(["B", "C"], [4, 4])
    assert r.since("C")["t"] == [3.0, 4.0] and r.since("A")["n"] == 0
    assert r.since("B")["t"] == [1.0, 2.0, 3.0, 4.0]


def test_an_accepted_proposal_shows_the_change_it_made_to_the_gains_in_force():
    """An advisory loop's proposals walk from the gains in force (each step adds a tenth
    of them on its track); accepting the third publishes the same gains again: its change
    is the one the acceptance made on the plant (1.3 / 1 - 1 = +30 %), not 0 against the
    proposal published before it (before: 0.0)."""
    from service.engine.config import LoopConfig
    from service.engine.engine import TuningEngine
    from service.learn.verification import StillAgent
    from service.wire.decode import decode_values

    class Raising(StillAgent):
        def act(self, obs, state, forgetting):  # a tenth of the gains observed a step
            return obs[:, :2] * 0.1, state

    engine = TuningEngine(Raising())
    engine.register(LoopConfig(
        id="A", kp=1.0, ki=0.1, sample_period_s=1.0, mode="advisory",
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, "excitation_periods": 0.0, "verify": False},
    ), wall=0.0)  # fmt: skip
    r = Recent(known=engine.table.slot_of)
    proposals = []
    for k in range(200):
        sample = {"loop_id": "A", "t": float(k), "sp": 1.0, "pv": 0.5, "kp": 1.0, "ki": 0.1}
        results = engine.ingest_decoded(decode_values([sample]), wall=float(k))
        results.append(engine.flush(float(k)))
        for result in filter(None, results):
            r.add_gains(result, wall=float(k))
            proposals.append(result)
        if len(proposals) == 3:
            break
    assert [round(p.new[0, 0], 6) for p in proposals] == [1.1, 1.2, 1.3]
    s = r.summary(["A"])
    assert s["dkp"][0] == pytest.approx(0.3)  # a proposal: against the gains in force too
    seq = engine.view("A", wall=200.0).proposal.seq
    r.add_gains(engine.accept("A", seq, wall=200.0), wall=200.0)
    s = r.summary(["A"])
    assert REASONS[s["reason"][0]] == "accepted"
    assert s["dkp"][0] == pytest.approx(0.3) and s["dki"][0] == pytest.approx(0.3)
