"""The periodic snapshot writes a chunk of loops at once (each of the table's arrays
read once for all of them): each loop's row must be what it is alone, aligned with its
own state, and restore to the same state."""

from __future__ import annotations

import math

import numpy as np
import orjson

from service.engine.config import LoopConfig
from service.engine.engine import TuningEngine
from tests.test_verify_engine import StillAgent, _responses


def _config(loop_id: str) -> LoopConfig:
    return LoopConfig(
        id=loop_id, kp=1.0, ki=0.05, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
    )  # fmt: skip


def test_a_chunk_snapshot_is_each_loops_own_and_restores_the_same_state():
    rng = np.random.default_rng(3)
    engine = TuningEngine(StillAgent())
    ids = [f"C{i}" for i in range(6)]
    for loop_id in ids:
        engine.register(_config(loop_id), wall=0.0)
    for loop_id in ids[:3]:  # responses (figures, history) on some loops only
        engine.ingest(_responses(loop_id, 0.0, 5, rng), wall=0.0)
    tb = engine.table
    s = tb.slot("C4")
    tb.g_iae[s], tb.cool_until[s], tb.last_e[s] = math.inf, -math.inf, 0.25  # JSON has no inf
    chunk = engine.snapshot()
    alone = [engine.snapshot([loop_id])[0] for loop_id in ids]
    assert sorted(chunk) == sorted(alone)
    runtime = {loop_id: orjson.loads(rt) for loop_id, _, rt in chunk}
    assert runtime["C4"]["verify"]["g_iae"] is None and runtime["C4"]["last_e"] == 0.25
    assert runtime["C0"]["figures"]["hist"] and not runtime["C5"]["figures"]["hist"]
    other = TuningEngine(StillAgent())
    for loop_id, hidden, rt in chunk:  # with the gains and seq the store has
        s = tb.slot(loop_id)
        stored = {"kp": float(tb.kp[s]), "ki": float(tb.ki[s]), "seq": int(tb.seq[s])}
        other.restore(_config(loop_id), **stored, hidden=hidden, runtime=rt, wall=0.0)
    assert sorted(other.snapshot()) == sorted(chunk)


def test_the_periodic_snapshot_writes_moved_loops_each_turn_and_the_others_in_rotation():
    """A loop whose agent stepped (or mode changed) since its last snapshot is in the
    next turn; one that only took samples waits for its turn in the rotation, which
    takes every loop within ``every`` turns."""
    engine = TuningEngine(StillAgent())
    ids = [f"R{i}" for i in range(8)]
    for loop_id in ids:
        engine.register(_config(loop_id), wall=0.0)
    tb = engine.table
    # as registered (the store's state: no row) or as last snapshotted: the rotation only
    assert [len(tb.snapshot_turn(turn, 4)) for turn in range(4)] == [2, 2, 2, 2]
    engine.snapshot()
    for i in range(30):  # samples only, no step: the running sums move
        engine.ingest([{"loop_id": x, "t": float(i), "e": 0.1} for x in ids], wall=0.0)
    assert int(tb.n_steps.sum()) == 0 and int(tb.n_samples.sum()) == 240
    turns = [tb.snapshot_turn(turn, 4) for turn in range(4)]
    assert all(len(t) == 2 for t in turns) and sorted(sum(turns, [])) == ids
    tb.n_steps[tb.slot("R1")] += 1  # a step
    tb.mode[tb.slot("R2")] = 1  # another mode
    assert set(tb.snapshot_turn(1, 4)) == {"R1", "R2", *turns[1]}
    engine.snapshot(["R1", "R2"])
    assert set(tb.snapshot_turn(1, 4)) == set(turns[1])
