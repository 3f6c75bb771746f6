"""What the operator is told about published changes (session 40's commissioning
review): ``counters.updates`` counts every gains message published and nothing else, an
advisory proposal shows the reason it was made for, the event log writes one gains line
per message published, a verdict's seqs after a rollback clipped by narrowed bounds are
a real range, and a model tuning's predicted effect comes from the model it was made on."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from service.agent import untrained_agent
from service.daemon import logs
from service.engine import TuningEngine, verify
from service.engine.audit import audit_row
from service.engine.patch import LoopPatch
from tests.test_first_tuning import engine_with
from tests.test_identify import TAU, drive, hinted
from tests.test_verify_engine import Pushing, _one_loop, _shadow_engine

pytestmark = pytest.mark.timeout(120)


class Unheeded:
    """The engine behind a gateway that applies no proposal (the operator decides): what
    :func:`tests.test_identify.drive` sees of it; ``published``: every update."""

    def __init__(self, engine: TuningEngine) -> None:
        self.engine, self.published = engine, []

    def view(self, loop_id: str, wall: float):
        return self.engine.view(loop_id, wall=wall)

    def ingest(self, samples: list[dict], wall: float) -> list:
        updates = self.engine.ingest(samples, wall=wall)
        self.published += updates
        return [u for u in updates if u.mode != "advisory"]


def _proposed_model_tuning():
    """An advisory hint-free loop whose model tuning is proposed and pending."""
    engine = engine_with(0.25, mode="advisory")
    gateway = Unheeded(engine)
    drive(gateway, moves=4)
    assert gateway.published[0].reason == "model"
    return engine, gateway.published


def test_updates_count_every_gains_message_published_of_every_kind():
    """A review's run: counters.updates summed 30 against 42 messages received (8 model
    tunings, 4 rollbacks left out); a loop tuned from its model showed updates 0."""
    engine = engine_with(0.25)  # hint-free, its gains a quarter of the model's tuning
    published = drive(engine, moves=6, every=12.0)
    assert {"model", "agent"} <= {u.reason for u in published}
    tb, s = engine.table, engine.table.slot("L")
    tb.kp[s] *= 1.3  # a change not yet judged: there is something to roll back
    published += engine.rollback("L", wall=1e9).updates()
    published += engine.reset("L", wall=1e9).updates()
    assert {u.reason for u in published} == {"model", "agent", "rollback", "reset"}
    assert engine.view("L", wall=1e9).counters.updates == len(published)
    # an advisory loop: its model tuning proposed, then accepted (one message each)
    advisory, proposed = _proposed_model_tuning()
    view = advisory.view("L", wall=1e9)
    accepted = advisory.accept("L", view.proposal.seq, wall=1e9).updates()
    assert [u.reason for u in accepted] == ["accepted"]
    assert advisory.view("L", wall=1e9).counters.updates == len(proposed) + 1


def test_a_shadow_loop_publishes_nothing_and_counts_no_update():
    engine = _shadow_engine(Pushing())
    samples = [{"loop_id": "S", "t": float(t), "e": 0.1} for t in range(0, 200)]
    assert engine.ingest(samples, wall=0.0) == []
    counters = engine.view("S", wall=0.0).counters
    assert counters.steps == 3 and counters.updates == 0  # counted 3 before


def test_an_advisory_proposal_shows_the_reason_it_was_made_for_and_keeps_it():
    """A model's tuning offered in advisory showed as an 'agent' proposal ("#8 (agent)" in
    the console) while its audit row said 'model'."""
    engine, published = _proposed_model_tuning()
    view = engine.view("L", wall=1e9)
    assert view.proposal.seq == published[-1].seq and view.proposal.reason == "model"
    # the reason survives a restart (the runtime snapshot)
    ((_, hidden, runtime),) = engine.snapshot()
    again = TuningEngine(untrained_agent(0))
    again.restore(engine.table.configs["L"], kp=view.kp, ki=view.ki, seq=view.seq,
                  hidden=hidden, runtime=runtime, wall=0.0)  # fmt: skip
    assert again.view("L", wall=1e9).proposal.reason == "model"
    # a rollback proposal says so, and an agent's step proposed says 'agent'
    tb, s = engine.table, engine.table.slot("L")
    verify.fail(tb, s, "iae", 1e9, figure=9.0)
    assert engine.view("L", wall=1e9).proposal.reason == "rollback"
    advisory = _shadow_engine(Pushing())
    advisory.reconfigure(LoopPatch(mode="advisory").apply(advisory.table.configs["S"]))
    samples = [{"loop_id": "S", "t": float(t), "e": 0.1} for t in range(0, 200)]
    assert [u.reason for u in advisory.ingest(samples, wall=0.0)] == ["agent"] * 3
    assert advisory.view("S", wall=0.0).proposal.reason == "agent"


def _message(loop_id, seq, reason="agent", mode="auto"):
    return {"v": 1, "loop_id": loop_id, "seq": seq, "t": 5.0, "dkp": 0.5, "dki": 0.05,
            "kp": 1.5, "ki": 0.15, "mode": mode, "reason": reason, "instance_id": "",
            "why": ""}  # fmt: skip


def test_the_event_log_writes_gains_lines_for_messages_published_only(caplog):
    """Held steps wrote "gains X -> X (agent, auto, seq 1)" lines: 4 for one loop against
    one message sent. Gains lines come from the messages published; the audit rows of
    decisions (published or not) write none, other rows say what they are."""
    events = logs.EventLog(logging.getLogger("pitune.events"), burst=20, interval_s=10.0)
    held = [
        audit_row("L0", 0.0, float(t), 1, "auto", "agent", (1.0, 0.1), (1.0, 0.1),
                  "reason=agent guard=model verdict=none")
        for t in (10, 20, 30)
    ]  # fmt: skip
    verified = audit_row("L0", 0.0, 40.0, 1, "auto", "verified", (1.5, 0.15), (1.5, 0.15),
                         '{"verdict":"verified","seqs":[1,1]}')  # fmt: skip
    with caplog.at_level(logging.INFO, "pitune.events"):
        events.audit([*held, audit_row("L0", 0.0, 5.0, 1, "auto", "agent", (1.0, 0.1),
                                       (1.5, 0.15)), verified])  # fmt: skip
        events.published([_message("L0", 1), _message("L1", 2, "reset")])
    messages = [r.getMessage() for r in caplog.records]
    assert messages == [
        "loop 'L0' verified (auto, kp=1.5 ki=0.15, seq 1) at t=40: "
        '{"verdict":"verified","seqs":[1,1]}',
        "loop 'L0' gains kp=1 ki=0.1 -> kp=1.5 ki=0.15 (agent, auto, seq 1) at t=5",
    ]  # one gains line per message (a reset's is the API's, with its caller)


def test_a_verdict_after_a_rollback_clipped_to_narrowed_bounds_judges_its_own_seq():
    """The last-good gains above bounds a PATCH narrowed: the rollback publishes them
    clipped, gains never judged; their verdict said "seqs":[19,18] (a review's run)."""
    engine, tb, s = _one_loop(0.4, 0.04)
    tb.g_kp[s], tb.g_ki[s], tb.g_iae[s] = 1.0, 0.1, 10.0  # verified since
    engine.reconfigure(LoopPatch(kp_max=0.6, ki_max=0.06).apply(tb.configs["L"]))
    tb.kp[s], tb.ki[s], tb.seq[s] = 0.5, 0.05, 5  # a step into the bounds, failed
    (rolled,) = verify.fail(tb, s, "iae", 100.0, figure=19.0).updates()
    assert (rolled.kp, rolled.ki, rolled.seq) == (0.6, 0.06, 6)
    assert engine.view("L", wall=0.0).verification.judged_seq == 5  # 6 is to be judged
    # their response completes, as good as the last-good figure: verified
    tb.f_iae[s], tb.f_move[s] = 10.5, 1.0
    tb.r_kp[s], tb.r_ki[s], tb.r_seq[s], tb.r_mixed[s] = 0.6, 0.06, 6, False
    assert verify.judge(tb, np.array([s]), np.array([], np.int64), 200.0) == []
    (row,) = [r for r in engine.drain_changes()[1] if r[5] == "verified"]
    assert json.loads(row[10])["seqs"] == [6, 6]
    assert engine.view("L", wall=0.0).verification.judged_seq == 6


def test_a_model_tuning_on_a_flagged_hint_predicts_its_effect_on_that_model():
    """A hint 3x too slow, flagged (not rescaled): the model tuning's audit row said
    "predicted":"prediction=none(no identified model)" right after the mismatch row
    holding the identified model."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted("A", tau_hat=3.0 * TAU), wall=0.0)
    drive(engine, "A", moves=6)
    _, audit = engine.drain_changes()
    reasons = [r[5] for r in audit]
    assert "mismatch" in reasons and "model" in reasons
    assert engine.view("A", wall=1e9).identification.in_force is None
    detail = json.loads(next(r for r in audit if r[5] == "model")[10])
    before, after = detail["predicted"].split()[0].removeprefix("pred_iae=").split("->")
    assert float(after) < 0.6 * float(before)  # the model's tuning: IAE -54 % on it
