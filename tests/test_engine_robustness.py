"""The engine's robustness measures of issue 12 (docs/tuner.md, Robustness measures):
the dead-time guard's gain margin and the noise damping, through the engine on simulated
loops."""

from __future__ import annotations

import numpy as np
import pytest

from service.engine.margin import gain_margin


def test_gain_margin_is_the_ultimate_gain_over_the_gains():
    """P-only on K exp(-s)/(s + 1): the ultimate gain is 2.262 (w180 = 2.029 rad/s, where
    atan(w) + w = pi); the margin scales as 1/c with both gains, and a first-order lag
    without dead time never reaches -180 degrees."""
    gm = gain_margin(np.array([1.0, 0.5, 2.0]), 1e-12, 1.0, 1.0, 1.0)
    assert gm == pytest.approx([2.2619, 4.5238, 1.1310], rel=1e-3)
    pi = gain_margin(0.4, 0.3, 2.0, 10.0, 20.0)
    assert gain_margin(0.8, 0.6, 2.0, 10.0, 20.0) == pytest.approx(pi / 2, rel=1e-9)
    assert np.isinf(gain_margin(5.0, 1.0, 1.0, 1.0, 0.0))


def _quiet_e_only(monkeypatch, sigmas: float) -> np.ndarray:
    """Final / initial gains of 3 grid loops (the oracle's gains) that send only the error,
    with noise 0.05 agent units and no setpoint move, over 30 RL periods."""
    from service.agent.model import load_agent
    from service.engine import rules
    from service.learn.oracle import oracle_gains, oracle_table
    from service.learn.robust import Condition, grid, run_condition

    monkeypatch.setattr(rules, "EXCITATION_NOISE_SIGMAS", sigmas)
    K, tau, r = (x[::13] for x in grid())
    g0 = oracle_gains(oracle_table(), K, tau, r * tau)
    cond = Condition("quiet, e only", noise=0.05, sp_hold=1e9)
    run = run_condition(load_agent(), cond, periods=30, gains0=g0, plants=(K, tau, r),
                        send_sp=False, seed=3)  # fmt: skip
    return run.gains[-1] / g0


def test_noise_alone_does_not_open_the_excitation_gate_of_an_e_only_loop(monkeypatch):
    """A gateway sending only e: a jump of the error between two samples counts as a
    setpoint move only beyond 5 noise sigmas of a difference (sqrt 2 sigma); before, noise
    of 0.05 agent units opened the gate (jumps of 0.2) and the agent walked the gains."""
    kept = _quiet_e_only(monkeypatch, 5.0)
    assert np.abs(kept - 1.0).max() < 1e-9
    walked = _quiet_e_only(monkeypatch, 0.0)
    assert np.abs(walked - 1.0).max() > 0.1
