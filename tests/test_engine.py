"""The tuning engine's public API: samples in, gain decisions out, no bus.

The engine is what the daemon runs; driven with the same samples it decides exactly
what the daemon publishes (checked against a real daemon on a real Zenoh bus).
"""

import numpy as np
import pytest
from pydantic import ValidationError

from service.agent import DEFAULT_WEIGHTS, load_agent, untrained_agent
from service.daemon.tuner import Tuner
from service.engine import GainUpdate, LoopConfig, TuningEngine
from service.learn.verification import StillAgent
from service.wire.protocol import RejectReason
from tests.test_tuner_tuning import STEPS, over_the_bus, run_plant, tank_config
from tests.tuner_support import GATE_OFF, connected_gateway, loop_body, tuner_settings

pytestmark = pytest.mark.timeout(120)


def through_the_engine(engine: TuningEngine):
    """``exchange`` (see ``run_plant``) through the engine's public API."""

    def exchange(loop_id, sample, due):
        updates = engine.ingest([{"loop_id": loop_id, **sample}], wall=sample["t"])
        assert len(updates) == due
        return updates[0] if due else None

    return exchange


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason=f"no trained agent at {DEFAULT_WEIGHTS}")
def test_the_engine_decides_exactly_what_the_daemon_publishes(tmp_path):
    config, scaling = tank_config()
    engine = TuningEngine(load_agent())
    engine.register(config)
    args = ("LIC-101", scaling, config.kp, config.ki, STEPS)
    by_engine = run_plant(through_the_engine(engine), *args)

    with Tuner(
        tuner_settings(tmp_path, inference_precision="float32"), agent=load_agent()
    ) as tuner:
        gateway = connected_gateway(tuner.settings)
        try:
            tuner.register(config)
            by_daemon = run_plant(over_the_bus(gateway), *args)
        finally:
            gateway.close()
    np.testing.assert_array_equal(by_engine, by_daemon)
    assert by_engine[-1, 0] > 3 * by_engine[0, 0]  # and it tuned: kp rose from the slow start


def test_many_loops_per_call_a_due_loop_is_stepped_before_its_next_sample():
    engine = TuningEngine(untrained_agent(0))
    for i in range(3):  # RL period 165 s, one sample per period
        engine.register(LoopConfig(**loop_body(f"L{i}", sample_period_s=165.0, guard=GATE_OFF)))
    first = [{"loop_id": f"L{i}", "t": 0.0, "e": 1.0} for i in range(3)]
    assert engine.ingest(first, wall=0.0) == []
    # L0 and L1 fall due at t = 165; L0's next sample comes in the same call: L0 and L1
    # are stepped first (one batched call), then L0 falls due again at the end
    samples = [
        {"loop_id": "L0", "t": 165.0, "e": 1.0},
        {"loop_id": "L1", "t": 165.0, "e": 1.0},
        {"loop_id": "L0", "t": 330.0, "e": 1.0},
    ]
    updates = engine.ingest(samples, wall=0.0)
    assert [(u.loop_id, u.seq, u.t) for u in updates] == [
        ("L0", 1, 165.0), ("L1", 1, 165.0), ("L0", 2, 330.0),
    ]  # fmt: skip
    assert all(isinstance(u, GainUpdate) and u.mode == "auto" and u.reason == "agent"
               for u in updates)  # fmt: skip
    assert engine.view("L0").kp == updates[-1].kp


def test_rejections_are_counted_and_reported_and_change_nothing():
    seen = []
    engine = TuningEngine(untrained_agent(0), on_reject=seen.append)
    engine.register(LoopConfig(**loop_body("L0", sample_period_s=1.0)))
    engine.ingest([{"loop_id": "L0", "t": 5.0, "e": 1.0}], wall=0.0)
    before = engine.view("L0")
    bad = [
        {"loop_id": "L0", "t": 5.0, "e": 1.0},  # duplicate
        {"loop_id": "L0", "t": 4.0, "e": 1.0},  # out of order
        {"loop_id": "nobody", "t": 6.0, "e": 1.0},
        {"loop_id": "L0", "t": "6", "e": 1.0},
        "not a sample",
    ]
    assert engine.ingest(bad, wall=0.0) == []
    assert [(r.index, r.reason) for r in sorted(seen, key=lambda r: r.index)] == [
        (0, RejectReason.duplicate), (1, RejectReason.out_of_order),
        (2, RejectReason.unknown_loop), (3, RejectReason.schema), (4, RejectReason.schema),
    ]  # fmt: skip
    assert engine.received == 6 and sum(engine.rejected.values()) == 5
    after = engine.view("L0")
    assert after.counters.rejected == 3 and after.counters.samples == before.counters.samples
    assert (after.kp, after.ki, after.int_e, after.last_sample_t) == (
        before.kp, before.ki, before.int_e, before.last_sample_t,
    )  # fmt: skip


@pytest.mark.parametrize(
    "bad",
    [
        {"kp": "1"},
        {"kp": True},
        {"sample_period_s": "1"},
        {"scaling": {"k_hat": "1.2", "tau_hat": 30.0}},
        {"guard": {"max_rel_change": "0.5"}},
        {"forgetting": "0.99"},
    ],
)
def test_registration_numbers_are_as_strict_as_the_wire(bad):
    """The REST API refuses a number given as a string, as the bus schema does (issue
    18, 4); an integer stays a number."""
    with pytest.raises(ValidationError, match="valid number"):
        LoopConfig(**{**loop_body("L0"), **bad})
    assert LoopConfig(**{**loop_body("L0"), "kp": 1}).kp == 1.0


def test_a_setpoint_move_of_any_size_looks_like_the_papers_to_the_agent():
    """Linear plants: moves of 0.6 and 3 agent units give the gains a +-1 square wave
    gives (the observation is scaled by 2 / move); 0.2 is past the bound (4) and differs."""
    from service.learn.robust import Condition, grid, run_condition

    plants = tuple(x[::9] for x in grid())  # 3 plants across K, tau, theta/tau
    agent = load_agent()

    def gains(amplitude: float) -> np.ndarray:
        run = run_condition(agent, Condition("a", sp_amplitude=amplitude), periods=12,
                            plants=plants)  # fmt: skip
        return run.gains

    paper = gains(1.0)
    assert not np.allclose(paper[-1], paper[0])  # the agent moved the gains
    np.testing.assert_allclose(gains(3.0), paper, rtol=1e-6)
    np.testing.assert_allclose(gains(0.3), paper, rtol=1e-6)
    assert not np.allclose(gains(0.1), paper, rtol=1e-3)


def test_the_setpoint_move_scaling_follows_the_last_move_and_survives_a_snapshot():
    eng = TuningEngine(load_agent())
    scaling = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 2.0}  # 1 agent unit = 2 PV units
    eng.register(LoopConfig(id="L", kp=0.5, ki=0.05, sample_period_s=1.0, scaling=scaling))
    tb = eng.table
    s = tb.slot("L")
    assert tb.obs_gain[s] == 1.0  # no move yet
    # moves further apart than the RL period (55 s here): each is measured on its own
    for t, sp, want in [(0, 10.0, 1.0), (100, 13.0, 4 / 3), (200, 12.0, 4.0), (300, 40.0, 0.25)]:
        eng.ingest([{"loop_id": "L", "t": t, "sp": sp, "pv": 10.0}], wall=t)
        assert tb.obs_gain[s] == pytest.approx(want)  # 2 / (move / 2), within [0.25, 4]
    ((loop_id, hidden, runtime),) = tb.snapshot(["L"])
    other = TuningEngine(load_agent())
    config = LoopConfig(id="L", kp=0.5, ki=0.05, sample_period_s=1.0, scaling=scaling)
    other.restore(config, kp=0.5, ki=0.05, seq=0, hidden=hidden, runtime=runtime)
    assert other.table.obs_gain[other.table.slot("L")] == 0.25


def test_a_ramp_is_one_move_of_its_whole_size_not_many_small_ones():
    """A setpoint ramped in steps of the smallest move (0.2 agent units) is measured from
    where it started while the steps come within one RL period of each other."""
    eng = TuningEngine(load_agent())
    scaling = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 2.0}  # RL period 55 s
    eng.register(LoopConfig(id="L", kp=0.5, ki=0.05, sample_period_s=1.0, scaling=scaling))
    tb, s = eng.table, eng.table.slot("L")

    def send(t: float, sp: float) -> float:
        eng.ingest([{"loop_id": "L", "t": t, "sp": sp, "pv": 10.0}], wall=t)
        return float(tb.obs_gain[s])

    send(0, 10.0)
    gains = [send(t, 10.0 + 0.4 * t) for t in range(1, 11)]  # 0 -> 2 agent units in 10 s
    assert gains[0] == pytest.approx(4.0)  # the first step alone: 0.2 units, bound 4
    assert gains[-1] == pytest.approx(1.0)  # the whole ramp: 2 units, as the paper's move
    assert send(20, 10.4) == pytest.approx(2 / (3.6 / 2))  # back down within the run
    assert send(200, 14.4) == pytest.approx(1.0)  # a later move on its own: 4 PV units


@pytest.mark.parametrize("shape", ["step", "staircase", "short ramp", "ramp"])
def test_the_agent_is_not_stepped_while_the_setpoint_ramps(shape):
    """RL periods within one RL period of a ramp's change (one continuing a ramp:
    service.units.ramp_rule) are quiet: the agent learned from step responses, and a
    ramp's lag, an error that grows as 1/ki, took it to gains far too high (docs/tuner.md,
    Setpoint ramps). An operator's second step in the same direction 29 s later is a step
    (session 26 gated it as a ramp, and tuned the bar's loops of issue 13 less), and so is
    a ramp shorter than an RL period once it has ended (units.RAMP_LONG)."""
    eng = TuningEngine(StillAgent())
    scaling = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 2.0}  # RL period 55 s, step 0.4
    guard = {"identify": False}
    eng.register(LoopConfig(id="L", kp=0.5, ki=0.05, sample_period_s=1.0, scaling=scaling,
                            guard=guard), wall=0.0)  # fmt: skip
    tb, s = eng.table, eng.table.slot("L")
    # 10 -> 14 PV units (2 agent units): at once, or a ramp over 200 s (a move about every
    # 20 s, each continuing the run)
    sp = {
        "step": lambda t: 14.0,
        "staircase": lambda t: 12.0 if t < 30 else 14.0,
        "short ramp": lambda t: 10.0 + 0.2 * min(t, 20),
        "ramp": lambda t: 10.0 + 0.02 * min(t, 200),
    }[shape]
    eng.ingest([{"loop_id": "L", "t": 0.0, "sp": 10.0, "pv": 10.0}], wall=0.0)
    stepped, pv = [], 10.0
    for t in range(1, 420):  # the PV follows a sample late (a PV held off its setpoint is
        # an output at a limit: service.engine.output_limit)
        eng.ingest([{"loop_id": "L", "t": float(t), "sp": sp(t), "pv": pv}], wall=float(t))
        pv = sp(t)
        if tb.n_steps[s] > len(stepped):
            stepped.append(t)
    if shape != "ramp":  # every RL period of the gate's window (4 periods after the move)
        assert stepped == [55, 110, 165, 220] and tb.n_quiet[s] == 3
        assert tb.ramp_t[s] == (20.0 if shape == "short ramp" else -np.inf)
        return
    # none while it ramps nor an RL period after its last step; then the gate's window
    assert 180.0 <= tb.ramp_t[s] <= 200.0
    assert len(stepped) == 3 and stepped[0] > tb.ramp_t[s] + 55.0
    assert tb.n_quiet[s] == 4  # the periods due at 55, 110, 165, 220
