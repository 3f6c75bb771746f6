"""Regulatory loops (issue 12's stretch item, service/learn/regulatory.py): a loop whose
setpoint never moves and that sees load steps, through the engine with the shipped agent."""

from __future__ import annotations

import pytest

from service.agent import DEFAULT_WEIGHTS, load_agent
from service.learn.regulatory import STARTS, disturbance_tuning, render
from service.learn.robust import grid

pytestmark = pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent")

PLANTS = tuple(x[[4, 13, 22]] for x in grid())
"""Three grid loops: K 0.25 / 0.5 / 1, tau 0.5, theta/tau 0.5 / 0.5 / 0.5."""


@pytest.fixture(scope="module")
def rows() -> dict:
    agent = load_agent()
    out = {}
    for gate in (True, False):
        table = disturbance_tuning(agent, periods=20, plants=PLANTS, excitation=gate)
        out[gate] = {(r["condition"], r["start"]): r for r in table}
    return out


def test_load_steps_alone_do_not_open_the_excitation_gate(rows):
    """The daemon's default: with the setpoint held, load steps never step the agent:
    every start's final gains are its start gains (same step-test MSE)."""
    for r in rows[True].values():
        assert r["worst_mse"] == pytest.approx(r["start_worst_mse"], rel=1e-9)
        assert r["median_mse"] == pytest.approx(r["start_median_mse"], rel=1e-9)
        assert r["improved"] == 0.0


def test_the_agent_left_to_step_on_disturbances_detunes_a_tuned_loop(rows):
    """Why the gate stays closed on disturbances (docs/tuner.md, Regulatory loops): from
    the oracle's gains the agent stepping on load responses alone ends every loop worse
    (step-test MSE 10-100x the oracle's on these loops), though it does raise badly
    detuned gains (kp = ki = 0.05): their MSE falls 15x in 20 RL periods."""
    off = rows[False]
    assert len(off) == 2 * len(STARTS)
    for (_, start), r in off.items():
        if start == "oracle":
            assert r["improved"] == 0.0 and r["median_mse"] > 10 * r["start_median_mse"]
        if start == "kp = ki = 0.05":
            assert r["median_mse"] < 0.1 * r["start_median_mse"]
    lines = render({"quiet_loop": {}, "disturbance_tuning": list(off.values())})
    assert sum(line.startswith("| load steps") for line in lines) == 2 * len(STARTS)
