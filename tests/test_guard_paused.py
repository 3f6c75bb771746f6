"""What a loop does in manual or saturation is not the gains' doing: no verdict comes of
it and it opens no excitation; and the robustness guard's cut stays within the bounds.

Each case is a loop driven through :class:`TuningEngine` with real samples (a simulated
FOPTD loop under PI control, or a hand-made PV record)."""

import numpy as np
import pytest

from plant_sim import FOPTDBatch, PIBatch
from service.agent.model import load_agent
from service.engine import LoopConfig, TuningEngine
from service.learn.robust import HINT, Condition, run_condition
from service.learn.verification import StillAgent
from service.units import ScalingSpec

pytestmark = pytest.mark.timeout(120)
K, TAU, THETA = 1.0, 10.0, 2.0
RAISE_AT, PAUSE_AT = 700, 890
"""An operator raises kp at 700 s; the setpoint moves at 880 s (every 220 s) and the loop
leaves auto (or saturates) 10 s into that response, before it is judged."""


@pytest.mark.parametrize("how", ["manual", "saturated"])
def test_a_response_that_runs_into_manual_or_saturation_is_not_judged(how):
    engine = TuningEngine(StillAgent())
    engine.register(LoopConfig(
        id="L", kp=2.5, ki=0.25, sample_period_s=1.0,
        scaling={"k_hat": K, "tau_hat": TAU, "pv_scale": 1.0},
        guard={"excitation_periods": 0.0, "identify": False},
    ), wall=0.0)  # fmt: skip
    plant = FOPTDBatch(np.array([K]), np.array([TAU]), np.array([THETA]), dt=1.0, max_theta=3.0)
    plant.reset(0.0)
    pi = PIBatch(np.array([2.5]), np.array([0.25]), dt=1.0, n=1, u_min=-10, u_max=10)
    pi.initialise(np.zeros(1))
    published, u = [], np.zeros(1)
    for k in range(1100):
        sp = 1.0 if (k // 220) % 2 == 1 else 0.0
        if k == RAISE_AT:  # a raise, not a detune: a failed response would be rolled back
            pi.set_gains(np.array([4.0]), np.array([0.25]))
        y = float(plant.output()[0])
        paused = k >= PAUSE_AT
        if not paused:  # in manual, or at its limit, the output stays where it was
            u = pi.step(np.array([sp - y]))
        sample = {"loop_id": "L", "t": float(k), "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0]), "auto": not (paused and how == "manual"),
                  "saturated": paused and how == "saturated"}  # fmt: skip
        for update in engine.ingest([sample], wall=float(k)):
            published.append((k, str(update.reason)))
            pi.set_gains(np.array([update.kp]), np.array([update.ki]))
        plant.step(u)
    assert (RAISE_AT + 15, "agent") in published  # (judged and stepped before the pause)
    assert not [p for p in published if p[0] >= PAUSE_AT], "nothing while paused"
    rows = engine.drain_changes()[1]
    assert not [r for r in rows if r[5] == "rollback"]
    view = engine.view("L", wall=1100.0)
    assert (view.kp, view.ki) == (4.0, 0.25)  # the operator's raise stands


class _Pushing(StillAgent):
    """Raises both gains 5 % every step it is given."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.05), state


@pytest.mark.parametrize("tracks", [False, True])
def test_a_setpoint_tracking_the_pv_in_manual_opens_no_excitation(tracks):
    """In manual from 100 s to 200 s the PV drifts 50 -> 51; the setpoint follows it or
    not; back in auto it is held: no move was made in auto, so nothing is stepped."""
    engine = TuningEngine(_Pushing())
    engine.register(LoopConfig(
        id="L", kp=1.0, ki=0.1, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0}, guard={"identify": False},
    ), wall=0.0)  # fmt: skip
    published = []
    for k in range(700):
        manual = 100 <= k < 200
        pv = 50.0 + 0.01 * (k - 100) if manual else (51.0 if tracks and k >= 200 else 50.0)
        sp = pv if manual and tracks else (51.0 if tracks and k >= 200 else 50.0)
        sample = {"loop_id": "L", "t": float(k), "sp": sp, "pv": pv, "auto": not manual}
        published += engine.ingest([sample], wall=float(k))
    assert published == []
    assert engine.view("L", wall=700.0).counters.quiet >= 8  # its periods counted quiet


def test_the_robustness_guard_never_cuts_below_the_lower_bounds():
    """A dead-time dominant loop (theta/tau = 2, outside the agent's box) identified with
    the guard's Ms 1.6: the agent's steps toward the bounds are cut, never past them
    (before: published 2x below kp_min and 2.6x below ki_min, then raised back by the
    model's tuning, a see-saw)."""
    scaling = ScalingSpec(**HINT).resolve()
    kp_min, ki_min = 0.3 * scaling.kp_per_agent, 0.6 * scaling.ki_per_agent
    guard = {"identify": True, "envelope_guard": False, "max_sensitivity": 1.6,
             "kp_min": kp_min, "ki_min": ki_min}  # fmt: skip
    plants = (np.array([1.0]), np.array([1.0]), np.array([0.1]))
    run = run_condition(load_agent(), Condition("theta/tau = 2", ratio=2.0), plants=plants,
                        guard=guard, gains0=np.array([[0.6, 1.2]]), periods=40)  # fmt: skip
    rows = [r for r in run.engine.table._audit if r[5] in ("agent", "model", "rollback")]
    assert any("guard=margin" in str(r[10]) for r in rows) or any(
        "guard=bounds" in str(r[10]) for r in rows
    )
    new = np.array([(r[8], r[9]) for r in rows])
    assert (new[:, 0] >= kp_min * (1 - 1e-9)).all() and (new[:, 1] >= ki_min * (1 - 1e-9)).all()
