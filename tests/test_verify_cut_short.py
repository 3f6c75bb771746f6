"""Setpoint moves closer than the 2 RL periods a response is judged over cut every
response short: no change is judged, and the verification view says so (a count that
survives a restart, and why the change is pending, with the numbers)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from plant_sim import FOPTDBatch, PIBatch
from service.engine import LoopConfig, TuningEngine
from service.learn.verification import StillAgent

pytestmark = pytest.mark.timeout(120)
K, TAU, THETA = 1.0, 10.0, 2.0
RL = 2.75 * 2 * TAU
"""The hint's RL period, s (time unit 2 tau_hat): a response is judged over 2 of them."""


class _Nudging(StillAgent):
    """Raises both gains 2 % every step it is given."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.02), state


def _run(engine: TuningEngine, moves: list[float], end: float, t0: float = 0.0) -> None:
    """The FOPTD loop under PI control from ``t0`` to ``end`` (1 s samples), the setpoint
    toggling 0 <-> 1 at the plant times ``moves``; the gains published reach the PI."""
    view = engine.view("L", wall=t0)
    plant = FOPTDBatch(np.array([K]), np.array([TAU]), np.array([THETA]), dt=1.0, max_theta=3.0)
    plant.reset(0.0)
    pi = PIBatch(np.array([view.kp]), np.array([view.ki]), dt=1.0, n=1, u_min=-10, u_max=10)
    pi.initialise(np.zeros(1))
    for k in range(int(t0), int(end)):
        sp = float(sum(m <= k for m in moves) % 2)
        y = float(plant.output()[0])
        u = pi.step(np.array([sp - y]))
        sample = {"loop_id": "L", "t": float(k), "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0])}  # fmt: skip
        for update in engine.ingest([sample], wall=float(k)):
            pi.set_gains(np.array([update.kp]), np.array([update.ki]))
        plant.step(u)


def test_changes_pending_because_every_response_is_cut_short_say_so_and_survive_a_restart():
    engine = TuningEngine(_Nudging())
    config = LoopConfig(
        id="L", kp=0.5, ki=0.05, sample_period_s=1.0,
        scaling={"k_hat": K, "tau_hat": TAU, "pv_scale": 1.0}, guard={"identify": False},
    )  # fmt: skip
    engine.register(config, wall=0.0)
    every = 80.0  # 1.45 RL periods: settled at each move (8 tau), never judged
    moves = [every * i for i in range(1, 13)]
    _run(engine, moves, 12 * every + 10)
    view = engine.view("L", wall=12 * every + 9)
    vf = view.verification
    assert view.counters.updates >= 10 and vf.pending and vf.judged_seq == 0
    assert vf.cut_short == 11  # the responses opened at moves 1..11, each cut by the next
    assert vf.unsettled_moves == 0  # (settled at every move: each opened one)
    m = re.fullmatch(
        r"since the last complete setpoint response 11 responses were cut short by the next "
        r"move \(the last after 80 s of the 110 s \(2 RL periods\) a response is judged "
        r"over\): no change is judged while the setpoint moves that often, and the changes "
        r"after seq 0 \(up to seq (\d+)\) wait for a verdict \(a rollback goes back to the "
        r"last-good gains of seq 0\)\. Next: let the loop settle and the setpoint stand 110 s "
        r"after a move now and then, or stop the automatic changes \(PATCH mode advisory or "
        r"frozen\)",
        vf.why,
    )
    assert m and int(m[1]) == view.seq
    # the count is in the runtime snapshot
    ((_, hidden, runtime),) = engine.snapshot()
    again = TuningEngine(_Nudging())
    again.restore(config, kp=view.kp, ki=view.ki, seq=view.seq, hidden=hidden,
                  runtime=runtime, wall=0.0)  # fmt: skip
    assert again.view("L", wall=0.0).verification.cut_short == 11
    # a response left to complete (no move for 200 s) sets the count back to 0
    _run(engine, [*moves, 13 * every, 13 * every + 200], 13 * every + 200 + 10, t0=12 * every + 10)
    after = engine.view("L", wall=13 * every + 209).verification
    assert after.cut_short == 0
    assert after.why is None or after.why.startswith("the changes after seq")


def test_moves_that_come_before_the_loop_settles_open_no_response_and_say_so():
    """The setpoint toggled every 15 s (1.5 tau; the loop is sluggish): no move finds the
    loop but the first within 20 % of it, none opens a response; the view counts them
    and says what share of its move the last one found left."""
    engine = TuningEngine(_Nudging())
    engine.register(LoopConfig(
        id="L", kp=0.5, ki=0.05, sample_period_s=1.0,
        scaling={"k_hat": K, "tau_hat": TAU, "pv_scale": 1.0}, guard={"identify": False},
    ), wall=0.0)  # fmt: skip
    _run(engine, [15.0 * i for i in range(1, 41)], 40 * 15 + 5)
    view = engine.view("L", wall=604.0)
    vf = view.verification
    assert vf.pending and vf.judged_seq == 0 and view.counters.updates >= 5
    # the first move found it settled and opened the one response, which the next cut
    assert (vf.cut_short, vf.unsettled_moves) == (1, 39)
    left = re.search(r"1 response was cut short by the next move \(the last after 15 s of "
                     r"the 110 s \(2 RL periods\) a response is judged over\) and 39 moves "
                     r"opened none, the loop not settled from the move before "
                     r"\(the last found (\d+) % of its move left; a response opens within "
                     r"20 % plus the noise\)", vf.why)  # fmt: skip
    assert left and int(left[1]) > 20


def test_an_operators_change_on_a_loop_without_a_model_says_what_it_waits_for():
    """A hint-free loop (no scaling yet) whose operator changed kp at t = 2: the why said
    "the changes after seq -1 (up to seq 0) ... then nan s (2 RL periods)"."""
    engine = TuningEngine(max_rate_hz=1e6)
    engine.register(LoopConfig(id="H", kp=0.1, ki=0.01, sample_period_s=1.0), wall=0.0)
    for t in range(5):
        sample = {"loop_id": "H", "t": float(t), "sp": 1.0, "pv": 0.9,
                  "kp": 0.1 if t < 2 else 0.2, "ki": 0.01}  # fmt: skip
        engine.ingest([sample], wall=float(t))
    view = engine.view("H", wall=5.0)
    assert view.kp == pytest.approx(0.2) and view.verification.pending
    assert view.verification.why.startswith(
        "the adopted gains (seq 0) wait for identification to put a model in force"
    )
    assert "nan" not in view.verification.why
