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
    for loop_id, hidden, rt in chunk:
        other.restore(_config(loop_id), kp=1.0, ki=0.05, seq=0, hidden=hidden, runtime=rt, wall=0.0)
    assert sorted(other.snapshot()) == sorted(chunk)
