"""The simulated plant's pace against its tuner (``--tuner-lag``): waits for a tuner that
makes progress, stops waiting for one that makes none, waits again when it is back.

The bus is not the subject: the gateway is an in-memory stand-in whose tuner answers
each state query as the real gateway sees it, the reply in the inbox once the plant
takes its messages (the bus side of the same run is ``tests/test_e2e.py``)."""

from types import SimpleNamespace

import pytest

from plant_sim import runner
from plant_sim.runner import TunerPace

LAG = 5.0


class Tuner:
    """A gateway with a tuner that, while ``up``, answers a state query with the samples
    it has accepted of each loop in ``answers`` and accepts ``rate`` more seconds of
    them each time the plant takes its messages (a tuner working through its backlog
    while the plant waits)."""

    def __init__(self, loops=("L",)) -> None:
        self.inbox = SimpleNamespace(supervision={})
        self.answers = set(loops)
        self.up = False
        self.reach = 0.0
        self.rate = 1.0
        self.queries = 0
        self.replies: list[tuple[str, float]] = []

    def query_state(self) -> None:
        self.queries += 1
        if self.up:
            self.replies += [(i, self.reach) for i in self.answers]

    def take_gains(self) -> None:
        """The plant takes its messages: the replies land in the inbox."""
        for i, t in self.replies:
            self.inbox.supervision[i] = SimpleNamespace(last_t=t)
        self.replies.clear()
        if self.up:
            self.reach += self.rate


def pace(tuner: Tuner, loops=("L",), stop=lambda: False) -> TunerPace:
    return TunerPace(tuner, list(loops), LAG, tuner.take_gains, stop)


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
    tuner.take_gains()
    p.hold(100.0)
    assert tuner.queries == 1 and p.waiting


def test_a_slow_tuner_making_progress_is_waited_for_beyond_the_give_up_time(quick):
    tuner = Tuner()
    tuner.up, tuner.rate = True, 0.5
    p = pace(tuner)
    p.hold(200.0)  # 390 polls of 2 ms: about 0.8 s, 4 x TUNER_WAIT_S
    assert p.waiting and p.accepted() >= 200.0 - LAG


def test_a_tuner_down_is_given_up_then_asked_once_a_recheck_then_waited_for_again(
    quick, monkeypatch, capsys
):
    tuner = Tuner()
    p = pace(tuner)
    p.hold(100.0)
    assert not p.waiting, "no tuner: the plant runs on"
    assert "no newer sample of L for 0.2 s" in capsys.readouterr().err
    monkeypatch.setattr(runner, "RECHECK_S", 3600.0)
    asked = tuner.queries
    for t in range(101, 200):
        tuner.take_gains()
        p.hold(float(t))
    assert tuner.queries == asked, "not waiting: no query before the recheck time"

    monkeypatch.setattr(runner, "RECHECK_S", 0.0)
    tuner.up, tuner.reach = True, 150.0  # started late, working through its backlog
    p.hold(300.0)  # the recheck's query
    assert not p.waiting, "no reply yet"
    tuner.take_gains()  # the scan loop takes the reply
    p.hold(301.0)  # against none before: progress
    assert p.waiting and p.accepted() >= 301.0 - LAG
    assert "making progress again" in capsys.readouterr().err


def test_a_tuner_that_stops_making_progress_is_given_up_again(quick):
    tuner = Tuner()
    tuner.up = True
    p = pace(tuner)
    p.hold(50.0)
    assert p.waiting
    tuner.up = False  # its last reply stays in the inbox, never newer
    p.hold(100.0)
    assert not p.waiting


def test_a_stop_ends_the_wait_at_once(monkeypatch):
    monkeypatch.setattr(runner, "TUNER_WAIT_S", 3600.0)
    calls = iter(range(1_000_000))
    tuner = Tuner()
    p = pace(tuner, stop=lambda: next(calls) >= 5)
    p.hold(100.0)  # a tuner down and an hour's patience: only the stop ends it
    assert p.waiting and tuner.queries == 5


def test_the_pace_is_the_slowest_loops_and_a_loop_never_answered_is_named(quick, capsys):
    tuner = Tuner(loops=("a", "b"))
    tuner.up = True
    tuner.answers = {"a"}  # b is not registered with this tuner
    p = pace(tuner, loops=("a", "b"))
    p.hold(50.0)
    assert not p.waiting and p.accepted() is None
    assert tuner.inbox.supervision["a"].last_t >= 50.0 - LAG, "a kept up all the while"
    assert "no newer sample of b for" in capsys.readouterr().err
