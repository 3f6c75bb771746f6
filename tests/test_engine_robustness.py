"""The engine's robustness measures of issue 12 (docs/tuner.md, Robustness measures):
the dead-time guard's gain margin and the noise damping, through the engine on simulated
loops."""

from __future__ import annotations

import numpy as np
import pytest

from service.engine.margin import gain_margin, robust_factor, sensitivity


def test_gain_margin_is_the_ultimate_gain_over_the_gains():
    """P-only on K exp(-s)/(s + 1): the ultimate gain is 2.262 (w180 = 2.029 rad/s, where
    atan(w) + w = pi); the margin scales as 1/c with both gains, and a first-order lag
    without dead time never reaches -180 degrees."""
    gm = gain_margin(np.array([1.0, 0.5, 2.0]), 1e-12, 1.0, 1.0, 1.0)
    assert gm == pytest.approx([2.2619, 4.5238, 1.1310], rel=1e-3)
    pi = gain_margin(0.4, 0.3, 2.0, 10.0, 20.0)
    assert gain_margin(0.8, 0.6, 2.0, 10.0, 20.0) == pytest.approx(pi / 2, rel=1e-9)
    assert np.isinf(gain_margin(5.0, 1.0, 1.0, 1.0, 0.0))


def test_the_robust_factor_brings_a_loop_to_the_sensitivity_bound():
    """Gains the agent left on dead-time dominant plants (robust suite, v2): scaled down
    together until Ms = 1.6 (gain margin then 3-4); good gains (Ms 1.04) untouched."""
    K, tau, th, kp, ki = np.array(
        [(1, 1, 2, 0.857, 2.38), (1, 3, 3, 0.589, 0.36), (0.5, 0.5, 0.05, 1.0, 1.0)]
    ).T
    c = robust_factor(kp, ki, K, tau, th, 1.6)
    assert c[:2] == pytest.approx([0.088, 0.418], abs=0.002) and c[2] == 1.0
    assert sensitivity(c[:2] * kp[:2], c[:2] * ki[:2], K[:2], tau[:2], th[:2]) == pytest.approx(
        1.6, abs=1e-3
    )


def test_the_robustness_guard_keeps_a_dead_time_dominant_loop_stable():
    """Through the engine (shipped agent, identification on): a plant of theta/tau = 2,
    outside the agent's training box, whose hint is right on K and tau. Without the guard
    the agent's gains after 80 RL periods left the step test unsettled (gain margin 1.3;
    MSE 0.86) while the agent read one error sample per period; with the window-mean
    observation (docs/tuner.md, Robustness measures 5) they settle without it too. With
    the guard (Ms <= 1.6 on the identified model) MSE 0.007."""
    from service.agent.model import load_agent
    from service.learn.robust import Condition, run_condition, score

    agent, plants = load_agent(), (np.array([1.0]), np.array([1.0]), np.array([0.1]))
    cond = Condition("theta/tau = 2", ratio=2.0)
    out = {}
    for ms in (0.0, 1.6):
        guard = {"identify": True, "envelope_guard": False, "max_sensitivity": ms}
        run = run_condition(agent, cond, plants=plants, guard=guard)
        out[ms] = score(run.K, run.tau, run.theta, run.lag, *run.gains[-1].T)
    assert not out[0.0][1][0]
    assert not out[1.6][1][0] and out[1.6][0][0] < 0.029


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
    of 0.05 agent units opened the gate (jumps of 0.2) and the agent walked the gains to
    0.18-1.13 of the oracle's in 30 RL periods."""
    kept = _quiet_e_only(monkeypatch, 5.0)
    assert np.abs(kept - 1.0).max() < 1e-9
    walked = _quiet_e_only(monkeypatch, 0.0)
    assert np.abs(walked - 1.0).max() > 0.1


def test_noise_damping_shortens_the_walk_of_a_tuned_loops_gains():
    """Through the engine (shipped agent): 3 grid loops from the oracle's gains, noise
    0.05 agent units, the setpoint held 8 RL periods (the gate's later periods see a
    decayed response: noise). With the damping (2 sigmas) the gains walk less on every
    loop: the summed |log change| 4.96, 2.75, 4.89 -> 3.83, 1.49, 2.61 over 48 periods."""
    from service.agent.model import load_agent
    from service.learn.oracle import oracle_gains, oracle_table
    from service.learn.robust import Condition, grid, run_condition

    agent = load_agent()
    K, tau, r = (x[[4, 13, 22]] for x in grid())
    g0 = oracle_gains(oracle_table(), K, tau, r * tau)
    cond = Condition("held, noisy", noise=0.05, sp_hold=22.0)
    path, worst = {}, {}
    for d in (0.0, 2.0):
        run = run_condition(agent, cond, periods=48, gains0=g0, plants=(K, tau, r), seed=4,
                            guard={"noise_damping": d})  # fmt: skip
        lg = np.log(run.gains / g0)
        path[d] = np.abs(np.diff(lg, axis=0)).sum(axis=(0, 2))
        worst[d] = np.abs(lg).max(axis=(0, 2))
    assert np.all(path[2.0] < 0.8 * path[0.0]) and np.all(worst[2.0] < worst[0.0])
