"""The bus's state reply says what holds a loop beyond its status (protocol revision 9):
``hold`` (the cool-down, the model check) and ``oscillating``, as the REST loop view does
(tests/test_status_holds.py drives the same cases through the engine alone). A real
tuner in-process on a real Zenoh bus; a gateway peer queries the ``state`` key with
``after_t`` (the reply waits for the loop's sample at that time: no sleeps)."""

import json

import numpy as np
import pytest

from plant_sim import FOPTDBatch, PIBatch
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import connected_gateway, tuner_settings

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def bus(tmp_path):
    tuner = Tuner(tuner_settings(tmp_path)).start()
    gateway = None
    try:
        gateway = connected_gateway(tuner.settings)
        yield tuner, gateway
    finally:
        if gateway is not None:
            gateway.close()
        tuner.stop()


def state_after(gw, loop_id: str, t: float) -> dict:
    """The loop's state reply once the tuner has its sample at plant time ``t``."""
    replies = list(gw.session.get(f"{gw.keys.state(loop_id)}?after_t={t!r}", timeout=5.0))
    assert len(replies) == 1 and replies[0].ok, replies
    state = json.loads(replies[0].ok.payload.to_bytes())
    assert state["last_t"] == t, state
    return state


def register(tuner, **guard) -> None:
    tuner.register(LoopConfig(
        id="L", kp=2.5, ki=0.25, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
        guard={"identify": False, **guard},
    ))  # fmt: skip


def test_the_state_reply_shows_the_cooldown_after_a_rollback_until_its_end(bus):
    """An operator's raise, rolled back on demand: the status still reads ``tuning``; the
    reply's hold names the cool-down and its end (8 RL periods), and is gone after it."""
    tuner, gw = bus
    register(tuner, excitation_periods=0.0)
    gains = {"kp": 2.5, "ki": 0.25}

    def send(k: int) -> dict:
        gw.send("L", {"t": float(k), "sp": 1.0, "pv": 0.9, **gains})
        return state_after(gw, "L", float(k))

    for k in range(20):
        assert send(k)["hold"] is None
    gains["kp"] = 4.0  # the operator's raise, adopted: a change pending
    assert send(20)["hold"] is None
    view = tuner.rollback("L")
    gains["kp"] = 2.5  # the gateway applies the rollback
    until = 20.0 + 8 * view.rl_period_s
    state = send(21)
    assert state["status"] == "tuning" and state["oscillating"] is False
    hold = state["hold"]
    assert hold["guard"] == "cooldown" and hold["since_t"] is None
    assert hold["until_t"] == pytest.approx(until) and f"until t = {until:.10g}" in hold["why"]
    k = 22
    while k < until:
        assert send(k)["hold"]["guard"] == "cooldown", k
        k += 1
    assert send(k)["hold"] is None


def test_a_loop_held_for_gains_out_of_bounds_that_oscillates_says_so_on_the_bus(bus):
    """An operator sets gains above kp_max that make the loop unstable: the status is
    ``gains_out_of_bounds`` and only ``oscillating`` tells the gateway the loop rings."""
    tuner, gw = bus
    register(tuner, kp_max=5.0)
    plant = FOPTDBatch(np.array([1.0]), np.array([10.0]), np.array([2.0]), dt=1.0,
                       max_theta=3.0, noise_std=0.01, seed=0)  # fmt: skip
    plant.reset(0.0)
    pi = PIBatch(np.array([2.5]), np.array([0.25]), dt=1.0, n=1, u_min=-100, u_max=100)
    pi.initialise(np.zeros(1))
    for k in range(880):
        if k == 700:
            pi.set_gains(np.array([8.0]), np.array([0.8]))
        y = float(plant.output()[0])
        sp = 1.0 if (k // 220) % 2 == 1 else 0.0
        u = pi.step(np.array([sp - y]))
        gw.send("L", {"t": float(k), "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                      "ki": float(pi.ki[0])})  # fmt: skip
        plant.step(u)
        if k == 699:
            calm = state_after(gw, "L", float(k))
            assert calm["oscillating"] is False and calm["status"] == "tuning"
    state = state_after(gw, "L", 879.0)
    assert state["status"] == "gains_out_of_bounds" and state["oscillating"] is True
    assert tuner.view("L").oscillating is True  # the REST view says the same
