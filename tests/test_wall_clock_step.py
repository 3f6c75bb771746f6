"""A wall clock stepped back (an NTP correction of -1 h, an operator's ``date``): a dead
gateway's loops still read ``stale`` once ``stale_gap`` has passed on a step-free clock,
while the audit keeps the wall time (service/engine/steady.py)."""

import time

from service.agent import untrained_agent
from service.daemon.tuner import Tuner
from service.engine import LoopConfig, TuningEngine
from service.wire.protocol import LoopStatus
from tests.tuner_support import loop_body, tuner_settings

W = 1.8e9
STEP_S = -3600.0


def _fed(engine: TuningEngine, walls, loop_id: str = "A") -> None:
    """20 samples, 1 s apart, each at the given wall time; then the gateway dies."""
    engine.register(LoopConfig(**loop_body(loop_id)), wall=walls(0))
    for k in range(20):
        sample = {"loop_id": loop_id, "t": float(k), "e": 0.1, "sp": 1.0, "pv": 0.9}
        engine.ingest([sample], wall=walls(k))


def test_a_dead_gateways_loop_is_stale_after_the_gap_though_the_wall_clock_stepped_back():
    steady = [W]
    engine = TuningEngine(untrained_agent(0), clock=lambda: steady[0])

    def walls(k: int) -> float:
        steady[0] = W + k
        return W + k

    _fed(engine, walls)
    died = W + 19
    seen, whys = {}, {}
    for real_s in (0, 60, 1800, 3500, 3700):
        steady[0] = died + real_s
        view = engine.view("A", wall=died + STEP_S + real_s)
        seen[real_s], whys[real_s] = view.status, view.status_why
    # (the wall clock alone said tuning at +60, +1,800 and +3,500 s: stale only at +3,700)
    assert seen == {
        0: LoopStatus.tuning,
        60: LoopStatus.stale,
        1800: LoopStatus.stale,
        3500: LoopStatus.stale,
        3700: LoopStatus.stale,
    }
    assert whys[1800].startswith("no sample for 1.8e+03 s, more than guard.stale_periods")
    # what is recorded keeps the wall clock, stepped or not
    engine.reset("A", wall=died + STEP_S + 60)
    (row,) = [r for r in engine.drain_changes()[1] if r[5] == "reset"]
    assert row[1] == died + STEP_S + 60


def test_without_a_step_free_clock_the_walls_passed_are_the_clock():
    engine = TuningEngine(untrained_agent(0))
    _fed(engine, lambda k: W + k)
    assert engine.view("A", wall=W + 19 + 5).status == LoopStatus.tuning
    assert engine.view("A", wall=W + 19 + 60).status == LoopStatus.stale


def test_the_tuner_measures_staleness_on_its_step_free_clock(tmp_path, monkeypatch):
    """The daemon's engine, fed as its worker feeds it (``clock.wall()``); then the host's
    wall clock steps back 1 h and 60 s pass: the loop reads stale, as it would have on
    a clock that did not step."""
    tuner = Tuner(tuner_settings(tmp_path), agent=untrained_agent(0))
    real_wall, real_mono = time.time, time.monotonic
    passed = [0.0]
    monkeypatch.setattr(time, "monotonic", lambda: real_mono() + passed[0])
    monkeypatch.setattr(time, "time", lambda: real_wall() + passed[0])

    def walls(k: int) -> float:
        passed[0] = float(k)
        return tuner.clock.wall()

    _fed(tuner.engine, walls)
    assert tuner.view("A").status == LoopStatus.tuning
    stepped = tuner.clock.wall()
    monkeypatch.setattr(time, "time", lambda: real_wall() + passed[0] + STEP_S)
    passed[0] += 60.0
    assert tuner.clock.wall() - stepped < STEP_S + 61.0  # the wall clock went back
    assert tuner.view("A").status == LoopStatus.stale
