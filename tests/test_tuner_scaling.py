"""Section 5.4 unit mapping: the paper's two-tank numbers and the PI equivalence."""

import numpy as np
import pytest
from pydantic import ValidationError

from plant_sim import FOPTDBatch
from service.units import RL_STEP_AGENT_UNITS, ScalingSpec

pytestmark = pytest.mark.timeout(30)


def test_paper_two_tank_numbers():
    # crude hint 1.2/(30 s + 1), data minus 55 cm divided by 10 cm
    s = ScalingSpec(k_hat=1.2, tau_hat=30.0, pv_scale=10.0).resolve()
    assert s.e_scale == pytest.approx(0.1)
    assert 1.2 * s.e_scale == pytest.approx(0.12)  # apparent gain after data scaling
    assert s.apparent_gain(1.2) == pytest.approx(0.5)  # after output scaling by 0.5/0.12
    assert 1.0 / s.u_scale == pytest.approx(0.5 / 0.12)
    assert round(s.apparent_gain(1.7), 2) == 0.71  # the true gain
    assert s.time_unit_s == pytest.approx(60.0)  # "sampling time every 30/0.5 = 60 s"
    assert round(s.apparent_tau(55.0), 2) == 0.92
    assert s.rl_period_s == pytest.approx(RL_STEP_AGENT_UNITS * 60.0) == pytest.approx(165.0)


def test_overrides_win_factor_by_factor():
    spec = ScalingSpec(k_hat=1.2, tau_hat=30.0, pv_scale=10.0, u_scale=2.0, time_unit_s=7.0)
    s = spec.resolve()
    assert (s.e_scale, s.u_scale, s.time_unit_s) == (pytest.approx(0.1), 2.0, 7.0)
    s = ScalingSpec(e_scale=0.5, u_scale=0.25, time_unit_s=3.0).resolve()  # no hint needed
    assert s.kp_per_agent == pytest.approx(2.0)
    assert s.ki_per_agent == pytest.approx(2.0 / 3.0)


@pytest.mark.parametrize(
    "body",
    [
        {"tau_hat": 30.0},  # no gain information
        {"k_hat": 1.2},  # no time information
        {"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0, "e_scale": 0.1},  # both
        {"k_hat": -1.2, "tau_hat": 30.0},
        {"k_hat": 1.2, "tau_hat": 0.0},
        {"k_hat": float("nan"), "tau_hat": 30.0},
        {"k_hat": 1e9, "tau_hat": 30.0, "e_scale": 1e9},  # derived u_scale absurd
        {"k_hat": 1.2, "tau_hat": 30.0, "bogus": 1},
    ],
)
def test_incomplete_or_absurd_specs_are_rejected(body):
    with pytest.raises(ValidationError):
        ScalingSpec(**body)


def test_gain_mapping_makes_the_same_controller():
    """A PI with mapped gains gives the same output in both unit systems, on a real loop.

    The engineering loop: the paper's true tank model 1.7 exp(-13 s)/(55 s + 1), 1 s
    samples. The agent-unit loop: the same plant as the agent sees it (gain 0.71, tau
    0.92, dead time 13/60). Driving both with the mapped gains must give outputs that
    agree after the inverse mapping.
    """
    s = ScalingSpec(k_hat=1.2, tau_hat=30.0, pv_scale=10.0).resolve()
    kp_a, ki_a = 0.8, 0.6
    kp, ki = s.to_engineering(kp_a, ki_a)
    assert s.to_agent(kp, ki) == pytest.approx((kp_a, ki_a))

    dt = 1.0
    eng = FOPTDBatch(1.7, 55.0, 13.0, dt=dt)
    agent = FOPTDBatch(s.apparent_gain(1.7), s.apparent_tau(55.0), 13.0 / 60.0, dt=dt / 60.0)
    sp_eng, integ_eng, integ_a = 10.0, 0.0, 0.0  # a 10 cm setpoint step
    for _ in range(600):
        e_eng = sp_eng - eng.output()[0]
        e_a = sp_eng * s.e_scale - agent.output()[0]
        assert e_a == pytest.approx(e_eng * s.e_scale, abs=1e-9)
        integ_eng += e_eng * dt
        integ_a += e_a * dt / 60.0
        u_eng = kp * e_eng + ki * integ_eng
        u_a = kp_a * e_a + ki_a * integ_a
        assert u_a == pytest.approx(u_eng * s.u_scale, rel=1e-9, abs=1e-12)
        eng.step(u_eng)
        agent.step(u_a)
    # the loop did something (settled near the setpoint), so the comparison meant something
    assert eng.output()[0] == pytest.approx(10.0, abs=1.0)
    assert np.isfinite(agent.output()).all()
