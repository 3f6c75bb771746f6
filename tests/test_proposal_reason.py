"""A pending proposal's reason survives a runtime snapshot by a fixed code
(:data:`service.engine.updates.REASON_CODE`): it was the reason's position in
:class:`UpdateReason`, which an added or reordered reason would silently move."""

from __future__ import annotations

import pytest

from service.engine import LoopConfig, TuningEngine
from service.engine.updates import REASON_CODE
from service.wire.protocol import UpdateReason
from tests.test_verify_engine import Pushing

pytestmark = pytest.mark.timeout(60)


def test_every_reason_has_its_own_fixed_code_those_of_session_40_kept():
    assert {str(r): c for r, c in REASON_CODE.items()} == {
        "agent": 0, "reset": 1, "rollback": 2, "accepted": 3, "model": 4,
    }  # fmt: skip
    assert set(REASON_CODE) == set(UpdateReason)


def _advisory() -> tuple[TuningEngine, LoopConfig]:
    """An advisory loop with an agent's proposal pending (seq 7, gains off the last-good)."""
    engine = TuningEngine(Pushing())
    config = LoopConfig(
        id="A", kp=1.0, ki=0.05, sample_period_s=1.0, mode="advisory",
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"excitation_periods": 0.0, "max_rel_change": 0.5},
    )  # fmt: skip
    engine.register(config, wall=0.0)
    engine.ingest([{"loop_id": "A", "t": float(t), "e": 0.1} for t in range(400)], wall=0.0)
    return engine, config


@pytest.mark.parametrize(
    ("stored", "reason"),
    [("0.0", "agent"), ("4.0", "model"), ("2.0", "rollback"), ("7.0", "agent"), ("null", "agent")],
)
def test_a_restored_proposal_keeps_the_reason_its_code_names(stored: str, reason: str):
    """Codes as snapshots of session 40 stored them (positions 0-4); 7, a later
    version's code, and none (a snapshot of before session 40) tell it from the gains
    (the proposal is not the last-good gains: agent); 7 raised an IndexError."""
    engine, config = _advisory()
    view = engine.view("A", wall=0.0)
    assert view.proposal.seq == 7 and view.proposal.reason == "agent"
    ((_, hidden, runtime),) = engine.snapshot()
    assert '"adv_why":0.0,' in runtime
    runtime = runtime.replace('"adv_why":0.0,', f'"adv_why":{stored},')
    again = TuningEngine(Pushing())
    again.restore(config, kp=view.kp, ki=view.ki, seq=view.seq, hidden=hidden,
                  runtime=runtime, wall=1.0)  # fmt: skip
    proposal = again.view("A", wall=1.0).proposal
    assert proposal.seq == 7 and proposal.reason == reason
