"""What a loop's view says beyond its status (service/engine/views.py): the agent held by
the cool-down or by the model check while the status reads ``tuning`` (``hold``), and an
oscillation under another status (``oscillating``). Each case is a loop driven through
:class:`TuningEngine` with real samples of a simulated FOPTD loop under PI control."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim import FOPTDBatch, PIBatch
from service.engine import LoopConfig, TuningEngine
from service.learn.verification import StillAgent
from service.wire.protocol import LoopStatus
from tests.test_identify import drive, hint_free

pytestmark = pytest.mark.timeout(120)


class _Pushing(StillAgent):
    """Raises both gains 0.3 agent units every step: off the model's tuning, where the
    model check holds such steps."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.3), state


def test_a_loop_whose_steps_the_model_check_holds_says_so_and_since_when():
    """A hint-free loop identified, its model's tuning in force (the agent held for the
    cool-down until its verdict): the agent's steps that the model check holds leave the
    status ``tuning`` and the gains unchanged; after each sample the view's hold names
    the cool-down while it lasts, then the model check and the plant time of the first
    held step of the run, until a step passes (before: nothing in the view said it)."""
    engine = TuningEngine(_Pushing())
    engine.register(hint_free(), wall=0.0)
    seen, steps = [], []  # (t, view, last agent step) after each sample; (t, held) of steps
    ingest = engine.ingest

    def watched(samples, wall):
        updates = ingest(samples, wall=wall)
        rows = engine.drain_changes()[1]
        steps.extend((r[2], "guard=model" in r[10]) for r in rows if r[5] == "agent")
        assert all(r[6:8] == r[8:10] for r in rows if "guard=model" in r[10])  # gains kept
        seen.append((samples[0]["t"], engine.view("L", wall=wall), steps[-1] if steps else None))
        return updates

    engine.ingest = watched
    drive(engine, moves=14, every=6.0)
    assert [held for _, held in steps] == [True, False, True, True]  # t 2760, 3008, 3256, 3500
    runs = {}  # the first held step of the run each held step belongs to
    for (t, held), prev in zip(steps, [None, *steps], strict=False):
        runs[t] = (runs[prev[0]] if prev and prev[1] else t) if held else None
    cooled = 0
    for t, view, last in seen:
        hold = view.hold
        if view.verification.held_until_t is not None:  # after the model's tuning
            assert hold.guard == "cooldown" and hold.until_t > t, t
            assert "cool-down after a model's tuning, until its verdict" in hold.why, t
            cooled += 1
        elif last is None or not last[1]:
            assert hold is None, t
        else:
            assert view.status == LoopStatus.tuning, t
            assert hold.guard == "model_check" and hold.until_t is None
            assert hold.since_t == runs[last[0]], t
            assert "model check" in hold.why and "guard=model" in hold.why
    assert cooled and seen[-1][1].hold.since_t == steps[2][0]  # the run of the last two
    assert seen[-1][1].counters.model_holds == 3


def test_the_cooldown_after_a_rollback_is_shown_with_its_end():
    """An operator's raise, rolled back on demand: the agent is held for the cool-down
    (8 RL periods) with the status still ``tuning``; the view's hold says until when, and
    is gone at the first sample past it."""
    engine = TuningEngine(StillAgent())
    config = LoopConfig(
        id="L", kp=2.5, ki=0.25, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, "excitation_periods": 0.0},
    )  # fmt: skip
    engine.register(config, wall=0.0)
    gains = {"kp": 2.5, "ki": 0.25}

    def sample(k: int):
        return {"loop_id": "L", "t": float(k), "sp": 1.0, "pv": 0.9, **gains}

    for k in range(20):
        engine.ingest([sample(k)], wall=float(k))
    gains["kp"] = 4.0  # the operator's raise, adopted: a change pending
    engine.ingest([sample(20)], wall=20.0)
    assert engine.view("L", wall=20.0).hold is None
    engine.rollback("L", wall=20.0)
    gains["kp"] = 2.5  # the gateway applies the rollback
    view = engine.view("L", wall=20.0)
    until = 20.0 + 8 * view.rl_period_s
    assert view.status == LoopStatus.tuning
    assert view.hold.guard == "cooldown" and view.hold.since_t is None
    assert view.hold.until_t == pytest.approx(until) == view.verification.held_until_t
    assert f"until t = {until:.10g}" in view.hold.why
    assert "the cool-down after a rollback (or its proposal)" in view.hold.why  # its cause
    ((_, hidden, runtime),) = engine.snapshot(["L"])  # a restarted tuner says the same
    other = TuningEngine(StillAgent())
    other.restore(config, kp=2.5, ki=0.25, seq=view.seq, hidden=hidden,
                  runtime=runtime, wall=20.0)  # fmt: skip
    assert other.view("L", wall=20.0).hold == view.hold
    k = 21
    while k < until:
        engine.ingest([sample(k)], wall=float(k))
        assert engine.view("L", wall=float(k)).hold.guard == "cooldown", k
        k += 1
    engine.ingest([sample(k)], wall=float(k))
    assert engine.view("L", wall=float(k)).hold is None


def test_a_loop_held_for_gains_out_of_bounds_that_oscillates_says_it_oscillates():
    """An operator sets gains above kp_max that make the loop unstable (kp 8 on K 1, tau
    10 s, theta 2 s): the tuner holds it (status ``gains_out_of_bounds``, the guard's
    action) and the view says it oscillates, as the detector does (before: only the
    status, which hid the oscillation)."""
    engine = TuningEngine(StillAgent())
    engine.register(LoopConfig(
        id="L", kp=2.5, ki=0.25, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, "kp_max": 5.0},
    ), wall=0.0)  # fmt: skip
    plant = FOPTDBatch(np.array([1.0]), np.array([10.0]), np.array([2.0]), dt=1.0,
                       max_theta=3.0, noise_std=0.01, seed=0)  # fmt: skip
    plant.reset(0.0)
    pi = PIBatch(np.array([2.5]), np.array([0.25]), dt=1.0, n=1, u_min=-100, u_max=100)
    pi.initialise(np.zeros(1))
    shown = []
    for k in range(1000):
        if k == 700:
            pi.set_gains(np.array([8.0]), np.array([0.8]))
        y = float(plant.output()[0])
        sp = 1.0 if (k // 220) % 2 == 1 else 0.0
        u = pi.step(np.array([sp - y]))
        sample = {"loop_id": "L", "t": float(k), "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0])}  # fmt: skip
        published = engine.ingest([sample], wall=float(k))
        assert k < 700 or published == [], k  # held: nothing published
        plant.step(u)
        view = engine.view("L", wall=float(k))
        shown.append((view.status, view.oscillating))
    assert all(not osc for _, osc in shown[:700])  # calm at the registered gains
    late = shown[800:]
    assert all(status == LoopStatus.gains_out_of_bounds for status, _ in late)
    # (a setpoint move, at 880 s, restarts the detector: 3 half-periods to flag again)
    assert sum(osc for _, osc in late) >= 0.9 * len(late) and late[-1][1]
    assert engine.performance("L").window.oscillating


def test_the_cooldown_after_a_rejected_proposal_names_the_rejection():
    """An advisory loop's proposal rejected by an operator: the hold names that cause (as
    the rollback's and the model's tuning's above name theirs)."""
    engine = TuningEngine(_Pushing())
    engine.register(LoopConfig(
        id="A", kp=1.0, ki=0.05, sample_period_s=1.0, mode="advisory",
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, "excitation_periods": 0.0},
    ), wall=0.0)  # fmt: skip
    ups = engine.ingest([{"loop_id": "A", "t": float(t), "e": 0.1} for t in range(100)], wall=0.0)
    assert ups and engine.view("A", wall=0.0).hold is None
    engine.reject("A", ups[-1].seq, wall=0.0)
    hold = engine.view("A", wall=0.0).hold
    assert hold.guard == "cooldown" and hold.until_t == pytest.approx(99.0 + 8 * 55.0)
    assert "the cool-down after an operator's rejection of a proposal" in hold.why
