"""The envelope guard's hysteresis: a loop leaves the agent's envelope beyond
``ENVELOPE_MARGIN`` (1.5x the training box) and comes back only within
``RESUME_MARGIN`` (about 1.36x), so a plant at the edge does not flap.

A hinted loop whose hint's tau is 3x the plant's (apparent tau 0.1667: the edge
0.25 / 1.5) paused and resumed at almost every assessment (the review's C-03: 12
pauses and 11 resumes in 3 h), its models' apparent tau 0.1663-0.1669.
"""

from __future__ import annotations

import json

import pytest

from plant_sim.scenario import FoptdLoop, LoopSettings
from service.engine import LoopConfig, TuningEngine, model_use
from service.engine.box import ENVELOPE_MARGIN, RESUME_MARGIN, TRAINING_BOX
from service.engine.identify import Model

pytestmark = pytest.mark.timeout(120)
HINT = {"k_hat": 2.0, "tau_hat": 60.0, "pv_scale": 1.0}
"""The plant's K, and 3x its tau (20 s): apparent tau at the envelope's edge."""


def test_a_plant_at_the_envelope_edge_is_paused_once():
    engine = TuningEngine(max_rate_hz=1e6)
    kp, ki = 0.125, 0.003125
    engine.register(LoopConfig(id="C", kp=kp, ki=ki, sample_period_s=1.0, scaling=HINT,
                               guard={"auto_rescale": False}), wall=0.0)  # fmt: skip
    settings = LoopSettings(kp=kp, ki=ki, sp_low=-1, sp_high=1, sp_period=200.0, noise=0.01)
    sim = FoptdLoop("C", settings, K=2.0, tau=20.0, theta=4.0, dt=1.0, seed=19)
    rows = []
    for _ in range(1100):
        sc = sim.scan()
        sample = {"loop_id": "C", "t": sc.t, "sp": sc.sp, "pv": sc.pv, "kp": sc.kp,
                  "ki": sc.ki, "op": sc.op}  # fmt: skip
        for up in engine.ingest([sample], wall=sc.t):
            sim.apply_gains(up.kp, up.ki)
        rows += [r for r in engine.drain_changes()[1] if r[5].endswith("_envelope")]
    # was: out at 600 s (apparent tau 0.16632), in at 664 s (0.16688), out 792, in 832,
    # out 992, in 1016
    taus = [json.loads(r[10])["tau"] for r in rows]
    assert [r[5] for r in rows] == ["out_of_envelope"], rows
    assert taus[0] == pytest.approx(TRAINING_BOX["tau"][0] / ENVELOPE_MARGIN, rel=0.01)
    view = engine.view("C", wall=1100.0)
    assert view.status == "out_of_envelope" and view.counters.envelope_pauses == 1
    # its latest model is still at the edge, inside the leaving margin
    assert view.identification.model.tau == pytest.approx(20.0, rel=0.01)


def _model(tau: float) -> Model:
    return Model(k=2.0, tau=tau, theta=4.0, noise=0.01, move=2.0, r2=0.999, k_rse=0.005,
                 tau_rse=0.005, events=4, confident=True)  # fmt: skip


def test_a_model_that_moves_across_pauses_and_resumes():
    """Confident models of the loop above, at apparent tau (0.5 x tau / 60 s) just out,
    just in, inside the leaving margin but not the resuming one, inside that, and just
    out again."""
    engine = TuningEngine(max_rate_hz=1e6)
    engine.register(LoopConfig(id="C", kp=0.125, ki=0.003125, sample_period_s=1.0,
                               scaling=HINT, guard={"auto_rescale": False}), wall=0.0)  # fmt: skip
    tb = engine.table
    s = tb.slot("C")
    leave = TRAINING_BOX["tau"][0] / ENVELOPE_MARGIN * 120.0  # 20 s: apparent 0.1667
    back = TRAINING_BOX["tau"][0] / RESUME_MARGIN * 120.0  # 22 s: apparent 0.1833
    assert back == pytest.approx(22.0)
    paused = []
    for t, tau in enumerate([leave * 0.999, leave * 1.001, back * 0.99, back * 1.01,
                             leave * 1.001, leave * 0.999]):  # fmt: skip
        model_use.envelope(tb, s, _model(tau), float(t), float(t), sure=True)
        paused.append(bool(tb.out_env[s]))
    assert paused == [True, True, True, False, False, True]
    rows = [r[5] for r in engine.drain_changes()[1] if r[5].endswith("_envelope")]
    assert rows == ["out_of_envelope", "in_envelope", "out_of_envelope"]


def test_theta_ratio_resumes_within_the_leaving_edge():
    """An exact hint (apparent gain and tau 0.5) on a plant at theta/tau 1.40, inside the
    envelope: one model at 1.55 pauses it, the next at the true 1.40 resumes it (with
    the resume margin on theta/tau too it stayed paused for good: no rescaling moves
    theta/tau, and only a model at 1.36 would have resumed it)."""
    engine = TuningEngine(max_rate_hz=1e6)
    engine.register(LoopConfig(id="D", kp=0.05, ki=0.001, sample_period_s=1.0,
                               scaling={"k_hat": 2.0, "tau_hat": 20.0, "pv_scale": 1.0}),
                    wall=0.0)  # fmt: skip
    tb = engine.table
    s = tb.slot("D")
    paused = []
    for t, ratio in enumerate([1.40, 1.55, 1.40, 1.40, 1.55]):
        m = Model(k=2.0, tau=20.0, theta=20.0 * ratio, noise=0.01, move=2.0, r2=0.999,
                  k_rse=0.005, tau_rse=0.005, events=4, confident=True)  # fmt: skip
        model_use.envelope(tb, s, m, float(t), float(t), sure=True)
        paused.append(bool(tb.out_env[s]))
    assert paused == [False, True, False, False, True]
    rows = [r[5] for r in engine.drain_changes()[1] if r[5].endswith("_envelope")]
    assert rows == ["out_of_envelope", "in_envelope", "out_of_envelope"]
