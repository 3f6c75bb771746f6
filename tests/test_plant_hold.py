"""The plant-wide hold through the engine (service/engine/plant_hold.py): while held no
loop is stepped (auto, advisory, shadow: no update, no proposal, the hidden state kept),
no model's tuning is put in force, the loops' views say so; the guard's rollback of a
change made before the hold and an operator's actions still go out; released, the
loops go on from where they were, with no step queued while held."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.engine import LoopConfig, TuningEngine
from service.engine.plant_hold import RELEASED, PlantHold
from service.learn.verification import StillAgent
from service.wire.decode import decode_values
from service.wire.protocol import LoopStatus, UpdateReason
from tests.test_identify import drive, hint_free
from tests.test_verify_engine import _feed, _lag, _overshoot, _still_loop

pytestmark = pytest.mark.timeout(120)
HELD = PlantHold(held=True, since=1_800_000_000.0, by="api", reason="DCS change window")
MODES = {"A": "auto", "V": "advisory", "S": "shadow"}
PERIOD = 55.0
"""The RL period of the loops below (tau_hat 10 s), plant seconds."""


class _Walking(StillAgent):
    """Raises both gains 0.05 agent units a step and counts its steps in its state."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.05), state + 1.0


def _engine() -> TuningEngine:
    engine = TuningEngine(_Walking())
    for loop_id, mode in MODES.items():
        engine.register(LoopConfig(
            id=loop_id, kp=1.0, ki=0.05, sample_period_s=1.0, mode=mode,
            scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
            guard={"identify": False, "excitation_periods": 0.0},
        ), wall=0.0)  # fmt: skip
    return engine


def _samples(t: float) -> list[dict]:
    return [{"loop_id": loop_id, "t": t, "e": 0.1} for loop_id in MODES]


def _run(engine: TuningEngine, start: int, stop: int) -> list:
    """One sample a second of every loop, plant times ``start`` to ``stop - 1``."""
    return [u for t in range(start, stop) for u in engine.ingest(_samples(float(t)), wall=t)]


def _state(engine: TuningEngine) -> dict:
    """What a step would change: gains, seq, counters, proposal, the agent's state."""
    tb = engine.table
    return {
        loop_id: (view.kp, view.ki, view.seq, view.counters.steps, view.counters.quiet,
                  view.proposal, float(tb.hidden[tb.slot(loop_id)].sum()))
        for loop_id in MODES
        for view in [engine.view(loop_id, wall=0.0)]
    }  # fmt: skip


def test_a_held_plant_steps_no_loop_and_goes_on_from_there_when_released():
    engine = _engine()
    before = _run(engine, 0, 330)  # steps at 55, 110, ..., 275
    assert {(u.loop_id, u.t) for u in before} == {
        (i, PERIOD * k) for i in ("A", "V") for k in range(1, 6)
    }  # (shadow steps are recorded, not published)
    walked = _state(engine)
    assert walked["A"][0] > 1.0 and walked["V"][5].kp > 1.0 and walked["S"][6] == 5.0
    # t = 330 ends a period: the loops fall due, and the hold comes before their step
    engine.ingest_decoded(decode_values(_samples(330.0)), wall=330.0)
    assert engine.due == 3
    engine.set_hold(HELD)
    assert engine.due == 0 and engine.flush(330.0) is None
    assert _run(engine, 331, 600) == []  # five periods end: no update, no proposal
    assert _state(engine) == walked  # nor a shadow step: the agent's state as it was
    for loop_id in MODES:
        view = engine.view(loop_id, wall=600.0)
        assert view.status == LoopStatus.tuning and view.hold.guard == "plant"
        assert view.hold.since_t is None and view.hold.until_t is None
        assert "set by api at 2027-01-15T08:00:00Z: DCS change window" in view.hold.why
    engine.set_hold(RELEASED)
    assert engine.view("A", wall=600.0).hold is None
    # the next period's end (605) steps each loop once: nothing queued while held
    after = _run(engine, 600, 700)
    assert sorted((u.loop_id, u.t) for u in after) == [
        ("A", 605.0),
        ("A", 660.0),
        ("V", 605.0),
        ("V", 660.0),
    ]
    assert after[0].kp - after[0].dkp == pytest.approx(walked["A"][0])  # from where it was
    assert {i: s[3] for i, s in _state(engine).items()} == {"A": 7, "V": 7, "S": 7}


def test_a_model_identified_while_held_is_put_in_force_without_its_tuning():
    """A hint-free loop: identification goes on under the hold (the model in force, the
    loop scaled), but its first tuning, which goes out without the hold, does not; the
    agent steps from the gains of before once released."""
    free = TuningEngine(StillAgent())
    free.register(hint_free(), wall=0.0)
    assert [u.reason for u in drive(free, moves=6)] == [UpdateReason.model]
    engine = TuningEngine(StillAgent())
    engine.register(hint_free(), wall=0.0)
    registered = engine.view("L", wall=0.0)
    engine.set_hold(HELD)
    assert drive(engine, moves=6) == []
    view = engine.view("L", wall=0.0)
    assert view.counters.identified == 1 and view.scaling is not None
    assert (view.kp, view.ki, view.seq) == (registered.kp, registered.ki, 0)
    assert [r[5] for r in engine.drain_changes()[1]] == ["identified"]
    engine.set_hold(RELEASED)
    later = drive(engine, moves=2, seed=1, t0=1e5)
    assert later and all(u.reason == UpdateReason.agent for u in later)
    assert (later[0].kp - later[0].dkp, later[0].seq) == (pytest.approx(registered.kp), 1)


def test_the_guards_rollback_of_an_earlier_change_and_operators_actions_go_out_while_held():
    """An operator's raise, pending when the plant is held, overshoots its next response:
    the rollback goes out (the undo wanted), while the agent, stepped without the hold,
    is not; an operator's reset goes out too."""
    engine, tb, s = _still_loop("V")
    t = _feed(engine, "V", 0.0, [0.0] * 60, [0.0] * 60)
    t = _feed(engine, "V", t, [1.0] * 220, _lag(0.0, 1.0, 10.0, 220))
    t = _feed(engine, "V", t, [0.0] * 220, _lag(1.0, 0.0, 10.0, 220))
    t = _feed(engine, "V", t, [0.0] * 10, [0.0] * 10, kp=2.0, ki=0.1)  # an operator's raise
    assert engine.view("V").verification.pending
    steps = int(tb.n_steps[s])
    assert steps > 0  # the agent is stepped up to the hold
    engine.set_hold(HELD)
    updates = []
    ingest = engine.ingest
    engine.ingest = lambda samples, wall: updates.extend(ingest(samples, wall=wall))
    t = _feed(engine, "V", t, [1.0] * 220, _overshoot(0.8), kp=2.0, ki=0.1)
    assert [(u.reason, u.kp) for u in updates] == [(UpdateReason.rollback, 1.0)]
    assert int(tb.n_steps[s]) == steps  # 4 RL periods ended: none stepped
    rolled = [r for r in engine.drain_changes()[1] if r[5] == "rollback"]
    assert json.loads(rolled[-1][10])["why"] == "overshoot"
    reset = engine.reset("V", wall=0.0, actor="api")
    assert reset is not None and reset.seq[0] == engine.view("V").seq
