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


def _dense_sensitivity(kp, ki, K, tau, theta) -> float:
    w = np.geomspace(1e-4, 1e6, 400_001) / (tau + theta)
    loop = (kp + ki / (1j * w)) * K * np.exp(-1j * theta * w) / (1j * tau * w + 1.0)
    return float(np.max(1.0 / np.abs(1.0 + loop)))


@pytest.mark.parametrize(
    "kp, ki, theta, ms",
    [(0.01, 1e5, 0.0, 313.1), (0.05, 50.0, 0.0, 6.819), (0.1, 400.0, 0.0005, 22.26)],
)
def test_the_sensitivity_finds_a_lightly_damped_peak(kp, ki, theta, ms):
    """PI on K 1, tau 1 s with little or no dead time and a large ki: a narrow peak near
    the gain crossover (316, 7.0, 20 rad/s). The frequency grid over tau + theta alone
    read Ms 0.111 (the peak beyond its top: the robust factor passed that loop as it was
    under a bound of 1.7), 6.27 and 19.4; now the dense scan's within 0.2 %, and the
    factor keeps each loop within the bound."""
    dense = _dense_sensitivity(kp, ki, 1.0, 1.0, theta)
    assert dense == pytest.approx(ms, rel=2e-3)
    assert sensitivity(kp, ki, 1.0, 1.0, theta)[0] == pytest.approx(dense, rel=2e-3)
    c = robust_factor(kp, ki, 1.0, 1.0, theta, 1.7)[0]
    assert c < 1.0 and _dense_sensitivity(c * kp, c * ki, 1.0, 1.0, theta) <= 1.701


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


def test_settling_scales_the_agents_step_by_its_steps_so_far():
    """``guard.settle_steps`` (docs/tuner.md, Robustness measures 7): the agent's asked-for
    change of the gains (log units) is taken whole for the first settle_steps steps of an
    episode, then scaled by settle_steps / n down to SETTLE_FLOOR; a decayed sum of asks
    beyond SETTLE_RESET starts n again; a new episode (reset) and a change of mode do too."""
    from service.agent.model import load_agent
    from service.engine import LoopConfig, TuningEngine
    from service.engine.patch import LoopPatch
    from service.engine.stepping import SETTLE_FLOOR, SETTLE_MEMORY, SETTLE_RESET, _settle

    eng = TuningEngine(load_agent())
    for i, steps in enumerate((20.0, 0.0)):
        eng.register(LoopConfig(id=f"L{i}", kp=1.0, ki=0.1, sample_period_s=1.0,
                                guard={"settle_steps": steps}))  # fmt: skip
    tb = eng.table
    s = np.array([tb.slot("L0"), tb.slot("L1")])
    on = tb.settle[s] > 0
    assert on.tolist() == [True, False]

    def taken(n_before: float, ask: float, acc: float = 0.0) -> float:
        tb.settle_n[s], tb.settle_kp[s], tb.settle_ki[s] = n_before, acc, 0.0
        old = np.column_stack([tb.kp[s], tb.ki[s]])
        new = _settle(tb, s, old * np.exp([[ask, -ask]] * 2), on)
        assert np.log(new[1] / old[1]) == pytest.approx([ask, -ask])  # off: whole
        share = np.log(new[0] / old[0]) / [ask, -ask]
        assert share[0] == pytest.approx(share[1])
        return float(share[0])

    assert taken(0.0, 0.1) == pytest.approx(1.0) and tb.settle_n[s[0]] == 1.0
    assert taken(19.0, 0.1) == pytest.approx(1.0)
    assert taken(39.0, 0.1) == pytest.approx(0.5)
    assert taken(999.0, 0.1) == pytest.approx(SETTLE_FLOOR)
    assert tb.settle_kp[s[0]] == pytest.approx(0.1)
    below = (SETTLE_RESET - 0.1) / SETTLE_MEMORY  # decays to just under the reset
    assert taken(999.0, 0.09, acc=below) == pytest.approx(SETTLE_FLOOR)
    assert taken(999.0, 0.11, acc=below) == pytest.approx(1.0)  # a real change: n again
    assert tb.settle_n[s[0]] == 1.0 and tb.settle_kp[s[0]] == 0.0
    tb.settle_n[s] = 50.0
    eng.reset("L0", wall=0.0)
    assert tb.settle_n[s[0]] == 0.0
    tb.settle_n[s] = 50.0  # a change of mode too: in shadow the asks were not applied
    eng.reconfigure(LoopPatch(mode="shadow").apply(tb.configs["L0"]))
    assert tb.settle_n[s[0]] == 0.0
    # PATCH /loops/{id} turns it off (and a bad value is refused)
    eng.reconfigure(LoopPatch(settle_steps=0.0).apply(tb.configs["L0"]))
    assert tb.settle[s[0]] == 0.0
    with pytest.raises(ValueError, match="greater than or equal to 0"):
        LoopPatch(settle_steps=-1.0)


def test_settling_steadies_a_noisy_loops_gains_and_follows_a_plant_that_moved():
    """Through the engine (shipped agent, forgetting 0.99): 3 grid loops, noise 0.05,
    irregular setpoints: the gains' largest deviation from their median over the last 80
    of 160 RL periods 0.25, 0.19, 0.09 without settling, 0.09, 0.12, 0.08 with it (v3:
    0.36, 0.17, 0.22 and 0.16, 0.05, 0.07): inside the issue's +-15 % on every loop, less
    on each, 0.52x in total; and after K doubles at period 80 (no noise, settled by then)
    the gains follow it down (kp from 1.61, 0.78, 0.50 to 0.61, 0.45, 0.23 in 40 periods)."""
    from service.agent.model import load_agent
    from service.learn.robust import Condition, grid, run_condition

    agent = load_agent()
    K, tau, r = (x[[4, 13, 22]] for x in grid())
    wander = {}
    for d in (0.0, 20.0):  # settling alone: the model check (identification) off
        run = run_condition(agent, Condition("noisy", noise=0.05, sp_irregular=True),
                            periods=160, plants=(K, tau, r), seed=1, forgetting=0.99,
                            guard={"settle_steps": d, "identify": False})  # fmt: skip
        late = run.gains[80:]
        wander[d] = np.abs(late / np.median(late, axis=0) - 1.0).max(axis=(0, 2))
    # A loop that already wanders little cannot lose 40 % of it: each loop less, all
    # inside the band, and the three together by 0.6x at least.
    assert np.all(wander[20.0] < wander[0.0]) and wander[20.0].max() < 0.15, wander
    assert wander[20.0].sum() < 0.6 * wander[0.0].sum(), wander
    run = run_condition(agent, Condition("paper protocol"), periods=120, plants=(K, tau, r),
                        seed=1, forgetting=0.99,
                        schedule=lambda p: (2 * K, tau, r * tau) if p == 80 else None)  # fmt: skip
    kp = run.gains[:, :, 0]
    assert np.all(kp[120] < 0.9 * kp[79]), kp[[79, 120]]


def test_a_hinted_loop_follows_a_slowing_plant_the_check_no_longer_describes():
    """Through the engine (shipped agent, default guard: the hint checked, the model
    check and verify-or-rollback on): the spread's tau ramp 0.25 -> 1 at K 0.46
    (``pitune evaluate --robust``'s adaptation). While the plant drifts its models are
    precise but their events disagree, so none is confident, and the check fell back on
    the model of before, which predicts every step toward the slower plant's gains worse:
    the gains stayed where they were from RL period 59 to 100 (model_check.stale sets
    that fallback aside). Then verification judged each step down against the IAE of the
    faster plant and rolled it back (verify.forget_figures drops those figures when the
    data show the plant moved). Step-test MSE on the slowed plant at the end: 0.070 in
    the 18-plant run before; on this run alone 0.022 without the figures dropped, 0.026
    without the fallback set aside, 0.0023 with both (0.00094 since the followed tuning
    also restarts the agent warmed on its model: the next test)."""
    from service.agent.model import load_agent
    from service.learn import robust_adaptation
    from service.learn.robust import score

    K0, tau0, theta, K1, tau1 = (x[12] for x in robust_adaptation.plants())
    assert (tau0, tau1) == (0.25, 1.0)
    run = robust_adaptation.run(load_agent(), [12])
    ki = run.gains[:, 0, 1]
    assert ki[100] < 0.5 * ki[59] and ki[140] < 0.35 * ki[59], ki[[59, 100, 140]]
    mse = score(run.K, run.tau, run.theta, run.lag, *run.gains[-1].T)[0][0]
    assert mse < 0.005, mse


def test_a_hinted_loop_takes_the_tuning_of_a_model_that_shows_its_gain_quadrupled():
    """Through the engine: the spread's K step 0.25 -> 1 (tau 0.44, theta 0.09). The
    models of the next 28 RL periods fit no excited event, so the check holds the
    agent's steps on the old model until the new one is confident (period 88); that
    model moved from the hinted loop's last (model_check.moved), so its tuning is put in
    force (hint_checked, ``followed``) and verification takes its response as a new
    baseline (verify.forget_figures). Without the follow the agent walked down from gains
    4x too high for the rest of the run (ki 0.36x its period-59 value at period 100,
    step-test MSE 0.00045 at the end); with it 0.26x and 0.00011 (0.000091 since the
    followed tuning restarts the agent warmed on its model)."""
    from service.agent.model import load_agent
    from service.learn import robust_adaptation
    from service.learn.robust import score

    K0, tau0, theta, K1, tau1 = (x[4] for x in robust_adaptation.plants())
    assert (K0, K1) == (0.25, 1.0)
    run = robust_adaptation.run(load_agent(), [4])
    ki = run.gains[:, 0, 1]
    assert ki[100] < 0.3 * ki[59], ki[[59, 100, 140]]
    mse = score(run.K, run.tau, run.theta, run.lag, *run.gains[-1].T)[0][0]
    assert mse < 0.0002, mse


def test_a_followed_plant_restarts_the_agent_warmed_on_its_model():
    """Through the engine: the paper's tau ramp (K 0.5, tau 0.4 -> 1, theta 0.1). After
    the ramp a confident model shows the plant moved and its tuning is followed (period
    108: kp 0.98, ki 1.09); the agent, its hidden state still the faster plant's, then
    walked kp down to 0.73 (step-test MSE 0.0017 at the end). Restarted from a state
    warmed on the followed model (first_tuning.WARMED), as after identification, it
    ends at kp 0.79: 0.00082."""
    from service.agent.model import load_agent
    from service.learn import robust_adaptation
    from service.learn.robust import score

    run = robust_adaptation.run(load_agent(), [0])
    assert (run.K[0], run.tau[0]) == (0.5, 1.0)
    followed = run.gains[101:, 0, 0] > 0.95  # the model's tuning in force
    assert followed.any(), run.gains[100:, 0]
    mse = score(run.K, run.tau, run.theta, run.lag, *run.gains[-1].T)[0][0]
    assert mse < 0.0012, mse
