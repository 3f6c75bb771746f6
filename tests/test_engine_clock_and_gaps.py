"""Plant time in the engine's holds and responses: a new plant clock (a gateway restarted
from 0) moves every hold with it; a response with a hole in its samples is not judged;
a sample that completes one response and opens the next is judged on the completed
one, and a move float32 cannot hold never raises inside a batch."""

import math

import numpy as np
import pytest

from service.engine import LoopConfig, TuningEngine
from service.engine.rules import CLOCK_RESET_SAMPLES
from service.learn.verification import StillAgent

HINT = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0}
"""RL period 55 s: a response is judged over the 110 s after its move."""


def _engine(*ids: str) -> TuningEngine:
    engine = TuningEngine(StillAgent())
    for loop_id in ids:
        engine.register(
            LoopConfig(id=loop_id, kp=1.0, ki=0.05, sample_period_s=1.0, scaling=HINT), wall=0.0
        )
    return engine


def test_a_new_plant_clock_moves_the_holds_with_it():
    engine = _engine("O")
    t0 = 30_000.0  # the gateway had run 8 h
    engine.ingest([{"loop_id": "O", "t": t0 + k, "e": 0.0, "kp": 3.0, "ki": 0.2}
                   for k in range(10)], wall=0.0)  # fmt: skip
    engine.rollback("O")  # the operator's: a cool-down and a fence
    tb, s = engine.table, engine.table.slot("O")
    left = {name: getattr(tb, name)[s] - tb.last_t[s] for name in ("cool_until", "x_until")}
    assert all(0.0 < v < math.inf for v in left.values()), left
    n = CLOCK_RESET_SAMPLES + 5
    engine.ingest([{"loop_id": "O", "t": float(k), "e": 0.0} for k in range(n)], wall=1.0)
    assert tb.last_t[s] == n - 1  # the new clock taken
    # as long to go as before, less the new clock's samples since it was taken
    for name, before in left.items():
        after = getattr(tb, name)[s] - tb.last_t[s]
        assert after == pytest.approx(before - (n - CLOCK_RESET_SAMPLES), abs=1.0), name


def _response(loop_id: str, times) -> list[dict]:
    """A first-order PV (tau 10 s) after a setpoint move 0 -> 1 at t = 10."""
    out, y = [], 0.0
    for t in times:
        sp = 1.0 if t >= 10 else 0.0
        y += (sp - y) / 10.0
        out.append({"loop_id": loop_id, "t": float(t), "sp": sp, "pv": y})
    return out


def test_a_response_with_a_gap_in_it_is_not_judged():
    full, cut = _engine("F"), _engine("C")
    full.ingest(_response("F", range(200)), wall=0.0)
    # the same samples stop 20 s into the response and come back 3 hours later
    cut.ingest(_response("C", [*range(30), *range(10_800, 10_900)]), wall=0.0)
    (done,) = full.performance("F").history
    assert done.iae == pytest.approx(10.0, rel=0.15)  # tau 10 s, a unit move
    assert cut.performance("C").history == []


def test_a_sample_completing_one_response_and_moving_the_setpoint_raises_nothing():
    engine = _engine("A", "B")
    for t in range(150):
        sp, e = (1.0, math.exp(-(t - 10) / 10.0) if t < 100 else 0.0) if t >= 10 else (0.0, 0.0)
        if t == 121:  # past the response's end, and a move float32 holds as 0
            sp, e = 0.0, 1e-50
        # A's operator changed its gains: the response judges them (overshoot, IAE)
        engine.ingest([{"loop_id": "B", "t": float(t), "sp": 0.0, "e": 0.0},
                       {"loop_id": "A", "t": float(t), "sp": sp, "e": e, "kp": 3.0, "ki": 0.2}],
                      wall=0.0)  # fmt: skip
    assert engine.view("A").counters.samples == engine.view("B").counters.samples == 150
    tb, s = engine.table, engine.table.slot("A")
    # the figures kept are the completed upward response's, its direction with them
    assert tb.f_move[s] > 0 and np.isfinite(tb.f_iae[s])
