"""The simulated plant's pace against its tuner (``--tuner-lag``): waits for a tuner that
makes progress, stops waiting for one that makes none, waits again when it is back.

The bus is not the subject: the gateway is an in-memory stand-in whose tuner answers
each state query (the bus side of the same run is ``tests/test_e2e.py``)."""

from types import SimpleNamespace

import pytest

from plant_sim import runner
from plant_sim.runner import TunerPace

LAG = 5.0


class Tuner:
    """A gateway whose tuner, while ``up``, answers each state query with the samples it
    has accepted, and accepts ``rate`` more seconds of them each time the plant takes its
    gains (a tuner working through its backlog while the plant waits)."""

    def __init__(self) -> None:
        self.inbox = SimpleNamespace(supervision={})
        self.up = False
        self.reach = 0.0
        self.rate = 1.0
        self.queries = 0

    def query_state(self) -> None:
        self.queries += 1
        if self.up:
            self.inbox.supervision["L"] = SimpleNamespace(last_t=self.reach)

    def take_gains(self) -> None:
        if self.up:
            self.reach += self.rate


def pace(tuner: Tuner) -> TunerPace:
    return TunerPace(tuner, ["L"], LAG, tuner.take_gains, lambda: False)


@pytest.fixture
def quick(monkeypatch):
    monkeypatch.setattr(runner, "TUNER_WAIT_S", 0.2)
    monkeypatch.setattr(runner, "RECHECK_S", 0.0)
    monkeypatch.setattr(runner, "POLL_S", 0.002)


def test_a_tuner_within_the_lag_costs_no_query(quick):
    tuner = Tuner()
    tuner.up, tuner.reach = True, 96.0
    p = pace(tuner)
    tuner.query_state()
    p.hold(100.0)
    assert tuner.queries == 1 and p.waiting


def test_a_slow_tuner_making_progress_is_waited_for_beyond_the_give_up_time(quick):
    tuner = Tuner()
    tuner.up, tuner.rate = True, 0.5
    p = pace(tuner)
    p.hold(200.0)  # 390 polls of 2 ms: about 0.8 s, 4 x TUNER_WAIT_S
    assert p.waiting and p.accepted() >= 200.0 - LAG


def test_a_tuner_down_is_given_up_then_asked_once_a_recheck_then_waited_for_again(
    quick, monkeypatch
):
    tuner = Tuner()
    p = pace(tuner)
    p.hold(100.0)
    assert not p.waiting, "no tuner: the plant runs on"
    monkeypatch.setattr(runner, "RECHECK_S", 3600.0)
    asked = tuner.queries
    for t in range(101, 200):
        p.hold(float(t))
    assert tuner.queries == asked, "not waiting: no query before the recheck time"

    monkeypatch.setattr(runner, "RECHECK_S", 0.0)
    tuner.up, tuner.reach = True, 150.0  # started late, working through its backlog
    p.hold(300.0)  # the recheck's query
    assert not p.waiting, "one reply is no progress yet"
    p.hold(301.0)  # its reply, against none before: progress
    assert p.waiting and p.accepted() >= 301.0 - LAG


def test_a_tuner_that_stops_making_progress_is_given_up_again(quick):
    tuner = Tuner()
    tuner.up = True
    p = pace(tuner)
    p.hold(50.0)
    assert p.waiting
    tuner.up = False  # its last reply stays in the inbox, never newer
    p.hold(100.0)
    assert not p.waiting and p.accepted() < 100.0 - LAG
