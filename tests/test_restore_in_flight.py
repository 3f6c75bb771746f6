"""An update still in flight when the tuner crashed is in flight after the restore: the
gateway's next samples, which may still report the gains it replaced, are not taken for
an operator's change (no 'adopted' row, the gains and a rollback's fence kept). The
restore has the store's gains and seq, and the last snapshot, written at that seq or one
update before it."""

import numpy as np
import pytest

from service.engine import LoopConfig, TuningEngine
from service.learn.verification import StillAgent

HINT = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0}
OLD = (1.0, 0.05)
"""The gains the DCS holds throughout: the update is never applied in these tests."""


class Pushing(StillAgent):
    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.2), state


def _config() -> LoopConfig:
    return LoopConfig(id="A", kp=OLD[0], ki=OLD[1], sample_period_s=1.0, scaling=HINT,
                      guard={"excitation_periods": 0.0})  # fmt: skip


def _sample(t: float) -> dict:
    return {"loop_id": "A", "t": t, "e": 0.1, "kp": OLD[0], "ki": OLD[1]}


def _first_update(engine: TuningEngine, snapshot_before: bool):
    """Samples until the agent's first update; the snapshot taken just before the
    sample that brought it, or right after it."""
    for t in range(200):
        before = engine.snapshot(["A"])
        (update, *_) = engine.ingest([_sample(float(t))], wall=0.0) or [None]
        if update is not None:
            return update, before if snapshot_before else engine.snapshot(["A"]), t
    raise AssertionError("no update")


@pytest.mark.parametrize("snapshot_before", [False, True])
def test_an_update_in_flight_stays_in_flight_across_a_restore(snapshot_before):
    engine = TuningEngine(Pushing())
    engine.register(_config(), wall=0.0)
    update, ((_, hidden, runtime),), t = _first_update(engine, snapshot_before)
    assert update.kp > OLD[0] and update.mode == "auto"
    restored = TuningEngine(Pushing())
    restored.restore(_config(), kp=update.kp, ki=update.ki, seq=update.seq, hidden=hidden,
                     runtime=runtime, wall=0.0)  # fmt: skip
    for e in (engine, restored):
        e.drain_changes()
        e.ingest([_sample(t + 1.0)], wall=1.0)  # the DCS has not applied it yet
        _, audit = e.drain_changes()
        assert "adopted" not in [row[5] for row in audit]
        # the update's gains, or (a snapshot before it: its RL period due again) the
        # next step's from them; never the DCS's old ones taken back
        assert e.view("A").kp >= update.kp and e.view("A").verification.pending


def test_two_updates_after_the_snapshot_leave_the_restore_as_registered():
    """What the second-to-last update replaced is unknown: the flag stays off."""
    engine = TuningEngine(Pushing())
    engine.register(_config(), wall=0.0)
    ((_, hidden, runtime),) = engine.snapshot(["A"])
    updates = engine.ingest([_sample(float(t)) for t in range(120)], wall=0.0)
    assert len(updates) == 2
    last = updates[-1]
    restored = TuningEngine(Pushing())
    restored.restore(_config(), kp=last.kp, ki=last.ki, seq=last.seq, hidden=hidden,
                     runtime=runtime, wall=0.0)  # fmt: skip
    assert not restored.table.pending[restored.table.slot("A")]


def test_after_a_restore_a_gateway_still_behind_is_not_taken_for_an_operator():
    """Two updates after the snapshot: whether an update is in flight is unknown, but a
    gateway reporting applied_seq below the seq is behind (an approval window), and the
    gains it reports are its last applied update's, not an operator's change."""
    engine = TuningEngine(Pushing())
    engine.register(_config(), wall=0.0)
    ((_, hidden, runtime),) = engine.snapshot(["A"])
    first, last = engine.ingest([_sample(float(t)) for t in range(120)], wall=0.0)
    restored = TuningEngine(Pushing())
    restored.restore(_config(), kp=last.kp, ki=last.ki, seq=last.seq, hidden=hidden,
                     runtime=runtime, wall=0.0)  # fmt: skip
    restored.drain_changes()
    behind = {"loop_id": "A", "t": 121.0, "e": 0.1, "kp": first.kp, "ki": first.ki,
              "applied_seq": first.seq}  # fmt: skip
    restored.ingest([behind], wall=1.0)
    assert restored.drain_changes() == ([], [])
    assert restored.view("A").kp == last.kp
