"""Identification restarted on a tuned loop (``POST /loops/{id}/identify``, or the
engine's own restart after a refuted model): nothing measured in the scaling that goes
is judged after it.

A hint-free loop (K 2, tau 20 s, theta 4 s, a sample a second, noise 0.01; setpoint
toggling +-1 every 200 s) under a DCS PI (plant_sim), identified and tuned by the engine
(the shipped agent; an auto loop: every update applied), asked to identify again at
t = 3010 s, 10 s after a setpoint move, while agent changes are pending. The response
opened at 3000 s was to be judged over two RL periods (past the next move at 3200 s);
with the scaling gone no move ended it, and at 3220 s it was judged with the new move's
error counted as overshoot (0.79 of the move; the loop's own overshoot was 0.0 %): the
changes were rolled back to the registered gains. The decimation window of before fell
due at 3060 s on the loop without a scaling: a ``fault`` audit row ("observation
non-finite").
"""

from __future__ import annotations

import pytest

from plant_sim.scenario import FoptdLoop, LoopSettings
from service.engine import LoopConfig, TuningEngine
from tests.test_identify_refuted import RINGING, _run

pytestmark = pytest.mark.timeout(120)
KP0, KI0 = 0.125, 0.003125
"""The registered (sluggish) gains."""
IDENTIFY_AT = 3010.0


def _reidentified(
    end: float = 3500.0, identify_at: float = IDENTIFY_AT, **config
) -> tuple[TuningEngine, list, dict, object]:
    """The loop (``config``: more of its LoopConfig) through the engine until ``end`` s,
    identified again at ``identify_at``; returns the engine, the audit rows from then on
    (as dicts), the loop's largest overshoot past the setpoint per 200 s of setpoint
    (share of the move) after it, and the view just before the identify."""
    engine = TuningEngine(max_rate_hz=1e6)
    engine.register(LoopConfig(id="X", kp=KP0, ki=KI0, sample_period_s=1.0, **config), wall=0.0)
    settings = LoopSettings(kp=KP0, ki=KI0, sp_low=-1, sp_high=1, sp_period=200.0, noise=0.01)
    sim = FoptdLoop("X", settings, K=2.0, tau=20.0, theta=4.0, dt=1.0, seed=0)
    over: dict[int, float] = {}
    rows, before = [], None
    for _ in range(int(end)):
        sc = sim.scan()
        sample = {"loop_id": "X", "t": sc.t, "sp": sc.sp, "pv": sc.pv, "kp": sc.kp,
                  "ki": sc.ki, "op": sc.op}  # fmt: skip
        for up in engine.ingest([sample], wall=sc.t):
            sim.apply_gains(up.kp, up.ki)
        if sc.t >= identify_at:
            part = int(sc.t // 200)
            over[part] = max(over.get(part, 0.0), (sc.pv - sc.sp) * (1 if sc.sp > 0 else -1) / 2)
        if sc.t == identify_at:
            before = engine.view("X", wall=sc.t)
            engine.identify("X", wall=sc.t, actor="test")
        rows += [r for r in engine.drain_changes()[1] if r[2] is not None and r[2] >= identify_at]
    names = ("loop_id", "wall", "t", "seq", "mode", "reason", "kp_old", "ki_old", "kp_new",
             "ki_new", "detail")  # fmt: skip
    return engine, [dict(zip(names, r, strict=True)) for r in rows], over, before


def test_identify_with_a_change_pending_rolls_nothing_back_and_faults_nothing():
    engine, rows, over, before = _reidentified()
    # the case: tuned, agent changes pending, a response open across the identify
    assert before.status == "tuning" and before.verification.pending
    assert before.kp > 1.5 * KP0 and before.verification.last_good_kp == pytest.approx(KP0)
    assert max(over.values()) < 0.01  # the responses did not overshoot
    reasons = [r["reason"] for r in rows if r["reason"] != "agent"]
    assert reasons[:2] == ["identify", "identified"], rows  # was: identify, fault, rollback
    assert "rollback" not in reasons and "fault" not in reasons
    view = engine.view("X", wall=3500.0)
    assert view.counters.faults == 0
    # the changes kept: the gains in force at the identify, or the agent's since
    assert view.kp >= before.kp and view.status == "tuning"
    assert abs(view.identification.in_force.tau / 20.0 - 1) < 0.05


def test_a_restart_after_a_refuted_model_faults_nothing():
    """The engine's own restart (the model's tuning rang and was rolled back) left the
    decimation window of before too: with no cool-down after the rollback to hold the
    agent past it, it fell due on the loop without a scaling (a ``fault`` row at 888 s,
    a period after the rollback at 736 s)."""
    engine, updates, view = _run(12, k_after_model=RINGING, ringing=True,
                                 guard={"cooldown_periods": 0.0})  # fmt: skip
    rows = engine.drain_changes()[1]
    assert [r[5] for r in rows if r[5] in ("rollback", "identify")] == ["rollback", "identify"]
    assert [r for r in rows if r[5] == "fault"] == [] and view.counters.faults == 0


def test_a_hinted_loop_back_on_its_hint_starts_a_fresh_episode():
    """A hinted loop (tau_hat 3x the plant's) rescaled by its model (RL period 110 s),
    identified again at 2010 s: back on its hint (RL period 330 s), its first step falls
    one hint period after the identify, at 2340 s; it fell at 2035 s, the old window's
    end, with a window of the old scaling's sums."""
    hint = {"k_hat": 2.0, "tau_hat": 60.0, "pv_scale": 1.0}
    engine, rows, _, before = _reidentified(
        2500.0, 2010.0, scaling=hint, guard={"auto_rescale": True}
    )
    assert before.scaling.time_unit_s == pytest.approx(40.0, rel=0.02)  # rescaled: tau 20 s
    assert engine.view("X", wall=2500.0).scaling.time_unit_s == pytest.approx(120.0)
    steps = [r["t"] for r in rows if r["reason"] == "agent"]
    assert steps[0] == pytest.approx(2010.0 + 330.0)
    assert [r for r in rows if r["reason"] in ("fault", "rollback")] == []


def test_a_change_pending_through_a_restart_waits_for_a_model_and_counts_afresh():
    """Just after the identify (changes pending, no scaling): the verification's why
    said "12 responses were cut short ... (the last after 200 s of the nan s ...) ...
    let the setpoint stand nan s after a move": the counts of the old scaling, and its
    RL period gone. It says the verdict waits for a model in force, and counts nothing."""
    engine, _, _, before = _reidentified(end=3012.0)
    assert before.verification.cut_short == 12
    view = engine.view("X", wall=3012.0)
    assert view.scaling is None and view.verification.pending
    assert view.verification.cut_short == 0 and view.verification.unsettled_moves == 0
    why = view.verification.why
    assert why.startswith("the changes after seq 0 (up to seq 8) wait for identification")
    assert "nan" not in why
