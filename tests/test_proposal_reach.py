"""An advisory loop's pending proposal stays safe to accept (session 41's review): the
agent's steps walk it no farther than its reach of the gains in force, an accept
re-checks it against the gains in force then, and it carries the plant time it was
made (docs/tuner.md, Advisory workflow)."""

from __future__ import annotations

import numpy as np
import pytest

from service.engine import LoopConfig, TuningEngine
from service.engine.patch import LoopPatch
from service.engine.track import REACH_STEPS
from service.learn.verification import StillAgent


class Pushing(StillAgent):
    """Always proposes kp and ki 0.2 agent units higher: its step never vanishes."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.2), state


def _advisory(rel: float = 0.5) -> TuningEngine:
    engine = TuningEngine(Pushing())
    engine.register(LoopConfig(
        id="A", kp=1.0, ki=0.05, sample_period_s=1.0, mode="advisory",
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"excitation_periods": 0.0, "max_rel_change": rel},
    ), wall=0.0)  # fmt: skip
    return engine


def _feed(engine, t0: float, n: int) -> list:
    """``n`` samples of 1 s from plant time ``t0``, the wall clock keeping pace."""
    ups = []
    for t in np.arange(t0, t0 + n, 100.0):
        batch = [
            {"loop_id": "A", "t": float(x), "e": 0.1} for x in np.arange(t, min(t + 100, t0 + n))
        ]
        ups += engine.ingest(batch, wall=float(t))
    return ups


def test_the_track_waits_at_its_reach_of_the_gains_in_force():
    engine = _advisory()
    ups = _feed(engine, 0.0, 4000)  # 72 RL periods of a step that never vanishes
    reach = 1.5**REACH_STEPS  # 3.375
    view = engine.view("A")
    p = view.proposal
    assert view.kp == 1.0 and p.kp == pytest.approx(reach) and p.ki == pytest.approx(0.05 * reach)
    assert p.at_reach and p.refused is None and p.seq == ups[-1].seq
    assert p.made_t == ups[-1].t < 3999.0  # made when it got there, not every period since
    # at its reach a step publishes nothing and takes no seq: the operator's seq stays good
    assert len(ups) < 40
    _, audit = engine.drain_changes()
    waits = [r for r in audit if r[5] == "agent" and "guard=reach" in r[10]]
    assert len(waits) > 30 and all("waits at its reach" in r[10] for r in waits)
    (accepted,) = engine.accept("A", p.seq).updates()
    assert accepted.kp == pytest.approx(reach)
    # from the gains accepted, the next proposals walk on (a few accepts reach far gains)
    engine.table.kp[0], engine.table.ki[0] = accepted.kp, accepted.ki  # the gateway applied it
    more = _feed(engine, 4000.0, 600)
    assert more and more[-1].kp > accepted.kp


def test_an_accept_rechecks_the_reach_against_the_gains_and_guard_in_force():
    engine = _advisory()
    _feed(engine, 0.0, 4000)
    seq = engine.view("A").proposal.seq
    # the rate limit narrowed since (3 steps of 10 %: 1.33x): the proposal lies beyond
    engine.reconfigure(LoopPatch(max_rel_change=0.1).apply(engine.table.configs["A"]))
    view = engine.view("A")
    assert view.proposal.seq == seq and "its reach" in view.proposal.refused
    with pytest.raises(ValueError, match=r"more than 1\.331x .* from the gains in force"):
        engine.accept("A", seq)
    assert engine.view("A").kp == 1.0  # nothing changed


@pytest.mark.parametrize("flag", ["oscillated", "out_of_envelope", "hint_mismatch"])
def test_an_accept_is_refused_when_the_loop_showed_the_plant_changed_since(flag):
    """Session 41's review: a model proposal made at t = 660 and accepted at t = 1300,
    after the plant's gain went 1 -> 4 and its dead time 2 -> 8, made the loop ring (|e|
    2.9 -> 6.6). What the tuner saw since the proposal was made refuses it."""
    engine = _advisory()
    _feed(engine, 0.0, 300)
    tb, p = engine.table, engine.view("A").proposal
    assert p.made_t == 275.0 and p.refused is None
    s = tb.slot("A")
    if flag == "oscillated":
        tb.osc_seen[s] = 290.0  # the detector flagged the loop after the proposal was made
        match = r"oscillated at t = 290, after the proposal was made \(t = 275\)"
    elif flag == "out_of_envelope":
        tb.out_env[s] = True
        match = "out of the agent's envelope"
    else:
        tb.mismatch[s] = True
        match = "mismatches the hint"
    assert engine.view("A").proposal.refused
    with pytest.raises(ValueError, match=match):
        engine.accept("A", p.seq)
    assert engine.view("A").kp == 1.0 and engine.view("A").proposal.seq == p.seq
