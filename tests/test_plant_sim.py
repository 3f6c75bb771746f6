"""Foundation numerics: FOPTD, PI, target, reference tunings, step metric, two-tank."""

import numpy as np
import pytest
from scipy.optimize import curve_fit

from plant_sim import (
    FOPTDBatch,
    PIBatch,
    oracle,
    simc,
    simc_improved,
    simc_paper,
    step_response,
    step_test,
    step_test_mse,
    to_parallel,
)
from plant_sim.two_tank import TwoTankBatch


@pytest.mark.parametrize("K,tau,theta", [(0.5, 1.0, 0.2), (1.0, 0.25, 0.0), (0.25, 0.7, 0.55)])
def test_foptd_matches_analytic_step_response(K, tau, theta):
    dt = 0.01
    plant = FOPTDBatch(K, tau, theta, dt=dt)
    ys = np.array([plant.step(1.0)[0] for _ in range(500)])
    t = dt * np.arange(1, 501)
    np.testing.assert_allclose(ys, step_response(K, tau, theta, t), atol=1e-3)


def test_dead_time_exact_to_one_sample():
    dt = 0.01
    plant = FOPTDBatch(1.0, 0.5, 0.37, dt=dt)
    ys = np.array([plant.step(1.0)[0] for _ in range(100)])
    first = np.argmax(ys > 0)  # sample index k+1 at which the output first moves
    assert abs((first + 1) * dt - (0.37 + dt)) <= dt + 1e-12


def test_foptd_parameter_change_keeps_output_continuous():
    plant = FOPTDBatch(0.5, 1.0, 0.1, dt=0.01)
    for _ in range(200):
        plant.step(1.0)
    before = plant.output().copy()
    plant.set_params(K=1.0, tau=0.4)
    assert plant.output() == pytest.approx(before)
    for _ in range(1000):
        plant.step(1.0)
    assert plant.output()[0] == pytest.approx(1.0, abs=1e-6)


def test_foptd_rejects_bad_parameters():
    with pytest.raises(ValueError):
        FOPTDBatch(1.0, -1.0, 0.0)
    plant = FOPTDBatch(1.0, 1.0, 0.1)
    with pytest.raises(ValueError):
        plant.set_params(theta=0.5)  # beyond the ring buffer reserved at construction


def test_load_disturbance_and_noise():
    plant = FOPTDBatch(2.0, 0.5, 0.0, dt=0.01, noise_std=0.1, seed=1)
    for _ in range(1000):
        plant.step(0.0, disturbance=1.0)
    assert plant.output()[0] == pytest.approx(2.0, rel=1e-6)
    samples = np.array([plant.measure()[0] for _ in range(4000)])
    assert samples.std() == pytest.approx(0.1, rel=0.05)


def test_vectorised_batch_equals_single_runs():
    rng = np.random.default_rng(0)
    n = 1000
    K, tau = rng.uniform(0.25, 1, n), rng.uniform(0.25, 1, n)
    theta = tau * rng.uniform(0, 1, n)
    kp, ki = rng.uniform(0.1, 2, n), rng.uniform(0.1, 3, n)
    batch = step_test(K, tau, theta, kp, ki, horizon=2.0)
    for i in range(0, n, 1):
        single = step_test(K[i], tau[i], theta[i], kp[i], ki[i], horizon=2.0)
        np.testing.assert_allclose(batch.y[i], single.y[0], rtol=0, atol=1e-12)


def test_pi_gain_changes_are_bumpless():
    pi = PIBatch(0.5, 0.2, dt=0.01)
    for e in np.linspace(1, 0.3, 50):
        u = pi.step(e)
    before = pi.output().copy()
    np.testing.assert_allclose(before, u)
    pi.set_gains(kp=1.7, ki=3.0)
    assert abs(pi.output()[0] - before[0]) < 1e-9
    # and the next sample moves only by the new gains' action on the error change
    e_next = 0.3
    assert pi.step(e_next)[0] == pytest.approx(before[0] + 3.0 * e_next * 0.01, abs=1e-12)


def test_pi_anti_windup_clamps_integral():
    pi = PIBatch(1.0, 10.0, dt=0.1, u_min=-1.0, u_max=1.0)
    for _ in range(100):
        u = pi.step(5.0)
    assert u[0] == 1.0
    assert pi.saturated[0]
    # integral did not wind up: a small negative error brings the output off the limit at once
    assert pi.step(-0.5)[0] < 1.0


def test_pi_reaches_its_limit_when_the_last_increment_would_cross_it():
    """Closed form: a static plant y = 0.5 u with the setpoint 8 needs u = 16 > 10, so
    the loop settles on the limit, pv = 5 (the integral frozen one increment short of
    it left u = 7.2, pv = 3.6, flagged saturated)."""
    pi, y = PIBatch(1.0, 0.7, dt=1.0, u_min=0.0, u_max=10.0), 0.0
    for _ in range(300):
        u = pi.step(8.0 - y)[0]
        y = 0.5 * u
    assert u == pytest.approx(10.0) and y == pytest.approx(5.0)
    assert pi.saturated[0]
    # the same loop with a setpoint it can hold is not saturated and unchanged by the limit
    pi, y = PIBatch(1.0, 0.7, dt=1.0, u_min=0.0, u_max=10.0), 0.0
    for _ in range(300):
        u = pi.step(3.0 - y)[0]
        y = 0.5 * u
    assert y == pytest.approx(3.0) and not pi.saturated[0]


def test_pi_gain_change_while_saturated_stores_no_windup():
    """Saturated high, the error grown to 8, kp lowered 1 -> 0.2: bumpless on the
    unclamped output (16) would raise the integral by 6.4 to 14.4, past the limit; the
    output must leave the limit as soon as the error turns (as without the change)."""
    pi = PIBatch(1.0, 0.5, dt=1.0, u_min=0.0, u_max=10.0)
    for e in [2.0] * 100 + [8.0] * 3:
        pi.step(e)
    integral = pi.integral[0]
    pi.set_gains(kp=0.2)
    assert pi.output()[0] == pytest.approx(10.0)  # still bumpless: on the limit
    assert pi.integral[0] == pytest.approx(max(integral, 10.0 - 0.2 * 8.0))
    assert pi.step(-0.1)[0] < 10.0
    # and while not saturated the change stays exactly bumpless
    free = PIBatch(1.0, 0.5, dt=1.0, u_min=0.0, u_max=10.0)
    free.step(2.0)
    before = free.output()[0]
    free.set_gains(kp=0.2)
    assert free.output()[0] == pytest.approx(before, abs=1e-12)


def test_simc_paper_reproduces_table_2():
    Kc, tau_I = simc_paper(0.5, 1.0, 0.2)
    assert Kc == pytest.approx(0.909, abs=5e-4)
    assert tau_I == pytest.approx(1.067, abs=5e-4)
    Kc, tau_I = simc_paper(0.25, 0.25, 0.1)
    assert Kc == pytest.approx(1.667, abs=5e-4)
    assert tau_I == pytest.approx(0.283, abs=5e-4)


def test_simc_rules():
    # original SIMC, tau_c = theta: Kc = tau/(2 K theta), tau_I = min(tau, 8 theta)
    Kc, tau_I = simc(2.0, 10.0, 1.0, 1.0)
    assert (Kc, tau_I) == pytest.approx((2.5, 8.0))
    Kc, tau_I = simc_improved(2.0, 10.0, 3.0, 3.0)
    assert (Kc, tau_I) == pytest.approx((11.0 / 12.0, 11.0))
    kp, ki = to_parallel(2.0, 4.0)
    assert (kp, ki) == (2.0, 0.5)


def test_step_test_target_and_metric():
    trace = step_test(0.5, 1.0, 0.2, 0.9, 0.85)
    assert trace.target[0, 0] == -1.0 and trace.y[0, 0] == -1.0
    # target is the delayed first-order response with tau_cl = 2 tau
    t = 0.01 * np.arange(trace.target.shape[1])
    np.testing.assert_allclose(trace.target[0], -1 + 2 * step_response(1.0, 2.0, 0.2, t), atol=1e-9)
    perfect = np.mean((trace.y - trace.target) ** 2)
    assert step_test_mse(0.5, 1.0, 0.2, 0.9, 0.85)[0] == pytest.approx(perfect)
    # the paper's initial tuning is far worse than SIMC
    slow = step_test_mse(0.5, 1.0, 0.2, 0.05, 0.05)[0]
    assert slow > 100 * step_test_mse(0.5, 1.0, 0.2, *to_parallel(*simc_paper(0.5, 1.0, 0.2)))[0]
    # unstable gains give inf, not NaN
    assert step_test_mse(1.0, 0.25, 0.25, 50.0, 500.0)[0] > 1.0


def test_the_filtered_step_test_is_the_simulations():
    """plant_sim.loop.step_test_mse_filtered (the engine's model check) against the
    simulation on 300 random loops, stable and unstable, dead time 0-3 tau."""
    from plant_sim.loop import step_test_mse_filtered

    rng = np.random.default_rng(3)
    n = 300
    K, tau = rng.uniform(0.1, 2.0, n), rng.uniform(0.1, 2.0, n)
    theta = tau * rng.uniform(0.0, 3.0, n)
    kp, ki = rng.uniform(0.05, 3.0, n), rng.uniform(0.05, 5.0, n)
    simulated = step_test_mse(K, tau, theta, kp, ki)
    filtered = step_test_mse_filtered(K, tau, theta, kp, ki)
    stable = simulated < 4.0
    assert 100 < stable.sum() < n  # both kinds drawn
    np.testing.assert_allclose(filtered[stable], simulated[stable], rtol=1e-9)
    assert (filtered[~stable] > 4.0).all() and not np.isnan(filtered).any()
    assert np.isinf(filtered).tolist() == np.isinf(simulated).tolist()


@pytest.mark.parametrize("K,tau,theta", [(0.5, 1.0, 0.2), (0.25, 0.25, 0.1), (1.0, 1.0, 1.0)])
def test_oracle_beats_simc(K, tau, theta):
    kp, ki, mse = oracle(K, tau, theta)
    simc_mse = step_test_mse(K, tau, theta, *to_parallel(*simc_paper(K, tau, theta)))[0]
    assert mse < simc_mse
    assert step_test_mse(K, tau, theta, kp, ki)[0] == pytest.approx(mse)


def test_two_tank_steady_state_inflow_equals_outflow():
    tank = TwoTankBatch(3, level_cm=[40.0, 55.0, 70.0])
    flow = tank.equilibrium_flow([40.0, 55.0, 70.0])
    for _ in range(600):
        tank.step(flow)
    np.testing.assert_allclose(tank.inflow, tank.outflow, rtol=1e-6)
    np.testing.assert_allclose(tank.level_cm, [40.0, 55.0, 70.0], atol=1e-6)
    assert flow[1] == pytest.approx(59.0, abs=0.5)  # Bernoulli at 55 cm: about 59 L/min


@pytest.mark.parametrize("scan", [1.0, 60.0])
def test_two_tank_settles_where_bernoulli_says_whatever_the_scan(scan):
    """Closed form: the level whose outflow pi r^2 f_c sqrt(2 g h) is the inflow. With 4
    integration substeps a scan, a 60 s scan settled at 31 cm for the 65 L/min that holds
    66.7 cm."""
    tank = TwoTankBatch(1, level_cm=55.0, dt=scan)
    for _ in range(int(3600 / scan)):
        tank.step(65.0)
    p = tank.p
    level_dm = (65.0 / (np.pi * p.r_pipe**2 * p.f_c)) ** 2 / (2.0 * p.g)
    assert tank.level_cm[0] == pytest.approx(10.0 * level_dm, abs=0.01)


def test_two_tank_units_by_foptd_fit():
    tank = TwoTankBatch(1, level_cm=55.0)
    f0 = tank.equilibrium_flow(55.0)
    ys = np.array([tank.step(f0 + 1.0)[0] for _ in range(900)]) - 55.0
    t = np.arange(1, 901, dtype=float)
    (K, tau, theta), _ = curve_fit(
        lambda t, K, tau, th: step_response(K, tau, th, t), t, ys, p0=[1.7, 55.0, 13.0]
    )
    assert 1.5 <= K <= 2.0  # cm per L/min
    assert 40.0 <= tau <= 65.0  # s
    assert 5.0 <= theta <= 25.0  # s, apparent dead time of the lags


def test_two_tank_level_clipped_and_noise_bounded():
    tank = TwoTankBatch(1, level_cm=100.0, noise_cm=1.0, seed=3)
    for _ in range(1200):
        tank.step(80.0)  # maximum pump flow overfills
    assert tank.level_cm[0] <= 121.92 + 1e-9
    noisy = np.array([tank.measure()[0] for _ in range(1000)]) - tank.x[0, 4] * 10
    assert np.abs(noisy).max() <= 1.0 and noisy.std() > 0.4
