"""The engine's loop table: integration, decimation, batching, safety guard, adoption,
snapshots. Parametrised ``batched`` tests run the engine's vectorised path and the scalar
reference (tests/engine_reference.py) on the same scenario."""

import contextlib
import math

import numpy as np
import orjson
import pytest

from service.agent import untrained_agent
from service.engine import TuningEngine
from service.engine.config import LoopConfig
from service.engine.modes import ADVISORY, AUTO
from service.engine.resets import PROPOSED
from service.engine.stepping import step
from service.engine.table import LoopTable
from service.wire.protocol import LoopStatus, RejectReason, Sample
from tests.engine_reference import Rejected, ingest_one, reference_ingest
from tests.tuner_support import GATE_OFF, loop_body

pytestmark = pytest.mark.timeout(30)
WALL = 1_000.0


class RecordingAgent:
    """The untrained agent, recording every batched call."""

    def __init__(self) -> None:
        self.inner = untrained_agent(0)
        self.cfg = self.inner.cfg
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []

    def act(self, obs, state, forgetting):
        self.calls.append((np.array(obs), np.array(forgetting)))
        return self.inner.act(obs, state, forgetting)


class ScalingAgent:
    """Proposes multiplying both gains by ``factor`` (to exercise the safety guard)."""

    def __init__(self, factor: float) -> None:
        self.cfg = untrained_agent(0).cfg
        self.factor = factor

    def act(self, obs, state, forgetting):
        delta = obs[:, :2] * (self.factor - 1.0)
        return delta, np.asarray(state) + 1.0


def table(agent=None, *, rate=1e6, **overrides) -> tuple[LoopTable, int]:
    """A table with one loop whose sample clock is 165 s (one sample per RL period)."""
    t = LoopTable(agent or untrained_agent(0), max_rate_hz=rate, capacity=2)
    slot = t.add(LoopConfig(**loop_body(**{"sample_period_s": 165.0, **overrides})), wall=WALL)
    return t, slot


def sample(t: float, e: float = 1.0, **kw) -> Sample:
    return Sample(t=t, e=e, **kw)


def feed(t: LoopTable, slot: int, times, errors=None) -> list[float]:
    """Ingest samples; return the sample times at which a step fell due."""
    errors = np.ones(len(times)) if errors is None else errors
    return [
        ti
        for ti, ei in zip(times, errors, strict=True)
        if ingest_one(t, slot, sample(ti, ei), WALL)
    ]


def test_trapezoid_integral_in_agent_units_on_irregular_timestamps():
    t, s = table(sample_period_s=1.0)
    times = np.array([0.0, 0.7, 2.0, 2.5, 4.1, 7.0])
    errors = np.array([1.0, -2.0, 3.0, 0.5, 0.0, 4.0])
    feed(t, s, times, errors)
    expected = np.trapezoid(errors, times) * 0.1 / 60.0  # e_scale 1/10, 60 s per agent unit
    assert t.int_e[s] == pytest.approx(expected, rel=1e-12)
    assert t.last_e[s] == 4.0


def test_decimation_follows_sample_time_not_arrival():
    t, s = table(sample_period_s=7.0)  # RL period 165 s
    times = np.arange(1000.0, 1700.0, 7.0)
    due = feed(t, s, times)
    # first window opens at the first sample; each step at the first sample past a boundary
    boundaries = 1000.0 + 165.0 * np.arange(1, 5)
    assert due == [float(times[times >= b][0]) for b in boundaries]
    # a slower sample clock (one sample every 400 s) skips boundaries without catching up
    t2, s2 = table(sample_period_s=400.0)
    assert feed(t2, s2, [0.0, 400.0, 800.0, 1200.0]) == [400.0, 800.0, 1200.0]
    assert t2.next_due[s2] == pytest.approx(1320.0)


def test_due_loops_are_stepped_in_one_batched_call_with_their_own_forgetting():
    agent = RecordingAgent()
    t = LoopTable(agent, max_rate_hz=1e6, capacity=1)  # grows while adding
    slots = [
        t.add(
            LoopConfig(**loop_body(f"L{i}", forgetting=0.9 + 0.01 * i, sample_period_s=165.0)),
            wall=WALL,
        )
        for i in range(3)
    ]
    for s, e in zip(slots, (1.0, -2.0, 0.5), strict=True):
        assert feed(t, s, [0.0, 165.0], [e, e]) == [165.0]
    result = step(t, np.array(slots), WALL)
    assert len(agent.calls) == 1
    obs, forgetting = agent.calls[0]
    np.testing.assert_allclose(forgetting, [0.9, 0.91, 0.92])
    kp_a, ki_a = 0.5 / (0.1 / 0.24), 0.01 / (0.1 / 0.24 / 60.0)
    np.testing.assert_allclose(obs[:, 0], kp_a)
    np.testing.assert_allclose(obs[:, 1], ki_a)
    np.testing.assert_allclose(obs[:, 2], [0.1, -0.2, 0.05])
    np.testing.assert_allclose(obs[:, 3], np.array([1.0, -2.0, 0.5]) * 0.1 * 165.0 / 60.0)
    assert result.loop_ids == ["L0", "L1", "L2"]
    assert list(result.seq) == [1, 1, 1]
    assert all(np.linalg.norm(t.hidden[s]) > 0 for s in slots)


def test_guard_limits_relative_change_then_bounds():
    t, s = table(ScalingAgent(10.0), guard={"max_rel_change": 0.25})
    feed(t, s, [0.0, 165.0])
    r = step(t, np.array([s]), WALL)
    np.testing.assert_allclose(r.proposed[0], [5.0, 0.1])
    np.testing.assert_allclose(r.new[0], [0.625, 0.0125])  # x1.25 at most
    assert (t.kp[s], t.ki[s]) == pytest.approx((0.625, 0.0125))
    assert "limited by the safety guard" in t.drain_changes()[1][-1][-1]

    t, s = table(ScalingAgent(0.01), guard={"kp_min": 0.45, "max_rel_change": 1.0})
    feed(t, s, [0.0, 165.0])
    r = step(t, np.array([s]), WALL)
    np.testing.assert_allclose(r.new[0], [0.45, 0.005])  # kp at its bound, ki halved


def test_gains_reported_outside_the_bounds_are_not_stepped_but_a_reset_ends_the_hold():
    """Not walked back (before session 37): such gains are an operator's choice beyond
    the bounds, or not the DCS's gains at all (docs/tuner.md, Behaviour)."""
    t, s = table(ScalingAgent(1.0), guard={"kp_max": 1.0, "max_rel_change": 0.5})
    ingest_one(t, s, sample(0.0, kp=4.0), WALL)  # an operator set kp far above the bound
    assert t.kp[s] == 4.0
    assert not ingest_one(t, s, sample(165.0, kp=4.0), WALL)
    assert t.status(s, WALL) is LoopStatus.gains_out_of_bounds
    t.reset(t.ids[s], WALL)  # the registered gains: the tuner's, within the bounds
    assert t.status(s, WALL) is not LoopStatus.gains_out_of_bounds


def test_advisory_publishes_but_keeps_the_gains():
    t, s = table(ScalingAgent(1.2), mode="advisory")
    feed(t, s, [0.0, 165.0])
    r = step(t, np.array([s]), WALL)
    np.testing.assert_allclose(r.new[0], [0.6, 0.012])
    assert (t.kp[s], t.ki[s]) == (0.5, 0.01)
    assert t.seq[s] == 1 and not t.pending[s]


def test_frozen_manual_saturated_and_stale_data_take_no_step():
    t, s = table(mode="frozen")
    assert feed(t, s, np.arange(0.0, 1000.0, 10.0)) == []
    assert t.status(s, WALL) is LoopStatus.frozen

    t, s = table()
    assert not ingest_one(t, s, sample(0.0), WALL)
    assert not ingest_one(t, s, sample(170.0, auto=False), WALL)  # due, but in manual
    assert t.status(s, WALL) is LoopStatus.manual
    assert not ingest_one(t, s, sample(340.0, saturated=True), WALL)
    assert t.status(s, WALL) is LoopStatus.saturated
    assert not ingest_one(t, s, sample(500.0), WALL)  # back in auto: a new window, due at 665
    assert ingest_one(t, s, sample(665.0), WALL)

    t, s = table(sample_period_s=1.0, guard={"stale_periods": 5.0})  # 5 s is stale
    feed(t, s, [0.0, 1.0, 2.0])
    int_before = t.int_e[s]
    assert not ingest_one(t, s, sample(170.0), WALL)  # gap: no step on data that spans it
    assert t.int_e[s] == int_before  # and no integration across it
    assert t.next_due[s] == 170.0 + 165.0
    assert t.status(s, WALL + 4.0) is LoopStatus.tuning
    assert t.status(s, WALL + 6.0) is LoopStatus.stale


@pytest.mark.parametrize("batched", [False, True])
def test_no_integration_in_manual_or_saturated_and_a_new_window_back_in_auto(batched):
    t, s = table(sample_period_s=1.0)
    ingest = ingest_one if batched else reference_ingest

    def take(t, s, smp):
        return ingest(t, s, smp, WALL)

    for k in range(101):  # 100 s in auto at e = 5 cm
        take(t, s, sample(float(k), e=5.0))
    in_auto = t.int_e[s]
    assert in_auto == pytest.approx(5.0 * 100.0 * 0.1 / 60.0)
    for k in range(101, 1201):  # 1000 s in manual, then 100 s saturated
        take(t, s, sample(float(k), e=5.0, auto=k > 1100, saturated=k > 1100))
    assert t.int_e[s] == in_auto
    assert not take(t, s, sample(1201.0, e=5.0))  # back in auto: a new window
    assert t.int_e[s] == in_auto and t.next_due[s] == 1201.0 + 165.0
    assert not any(take(t, s, sample(float(k), e=5.0)) for k in range(1202, 1366))
    assert t.int_e[s] == pytest.approx(in_auto + 5.0 * 164.0 * 0.1 / 60.0)
    assert take(t, s, sample(1366.0, e=5.0))


def test_reported_gains_are_adopted_unless_an_update_is_in_flight():
    t, s = table(ScalingAgent(1.2))
    feed(t, s, [0.0, 165.0])
    step(t, np.array([s]), WALL)
    t.drain_changes()
    assert t.kp[s] == pytest.approx(0.6)
    ingest_one(t, s, sample(166.0, kp=0.5, ki=0.01), WALL)  # gateway not caught up yet
    assert t.kp[s] == pytest.approx(0.6)
    ingest_one(t, s, sample(167.0, kp=0.6, ki=0.012), WALL)  # applied
    assert not t.pending[s]
    ingest_one(t, s, sample(168.0, kp=0.5, ki=0.01), WALL)  # now an operator's change
    assert (t.kp[s], t.ki[s]) == (0.5, 0.01)
    gains, audit = t.drain_changes()
    assert gains == [(0.5, 0.01, 1, "LIC-101")]
    assert [row[5] for row in audit] == ["adopted"]


def _two_updates_ahead(batched: bool):
    """A loop stepped twice (seq 2: 0.5 -> 0.6 -> 0.72) whose gateway applied neither."""
    t, s = table(ScalingAgent(1.2))
    feed(t, s, [0.0, 165.0])
    step(t, np.array([s]), WALL)
    feed(t, s, [330.0])
    step(t, np.array([s]), WALL)
    t.drain_changes()
    assert int(t.seq[s]) == 2 and t.kp[s] == pytest.approx(0.72) and t.pending[s]
    return t, s, ingest_one if batched else reference_ingest


@pytest.mark.parametrize("batched", [False, True])
def test_a_lagging_gateway_reporting_applied_seq_is_not_adopted(batched):
    t, s, ingest = _two_updates_ahead(batched)
    ingest(t, s, sample(331.0, kp=0.5, ki=0.01, applied_seq=0), WALL)  # two updates behind
    assert t.kp[s] == pytest.approx(0.72) and t.pending[s]
    assert t.drain_changes() == ([], [])
    ingest(t, s, sample(332.0, kp=0.6, ki=0.012, applied_seq=1), WALL)  # one behind
    assert t.kp[s] == pytest.approx(0.72) and t.pending[s]
    ingest(t, s, sample(333.0, kp=0.72, ki=0.0144, applied_seq=2), WALL)  # caught up
    assert not t.pending[s] and t.drain_changes() == ([], [])


@pytest.mark.parametrize("batched", [False, True])
def test_after_advisory_steps_an_operators_change_in_auto_is_adopted(batched):
    """Advisory steps raise seq without anything to apply: back in auto, the gateway's
    applied_seq (its last auto update, 1) stays below seq (3) until the next auto update.
    With no auto update in flight that is no lag: gains it reports are an operator's
    (they went unseen, and the next auto step overwrote them: an integrator's review)."""
    t, s = table(ScalingAgent(1.2))
    ingest = ingest_one if batched else reference_ingest
    feed(t, s, [0.0, 165.0])
    step(t, np.array([s]), WALL)  # seq 1, auto: 0.5 -> 0.6
    ingest(t, s, sample(166.0, kp=0.6, ki=0.012, applied_seq=1), WALL)
    assert not t.pending[s]
    t.mode[s] = ADVISORY
    for k in (330.0, 495.0):
        feed(t, s, [k])
        step(t, np.array([s]), WALL)
    t.mode[s] = AUTO
    t.drain_changes()
    assert int(t.seq[s]) == 3 and not t.pending[s]
    ingest(t, s, sample(496.0, kp=0.4, ki=0.01, applied_seq=1), WALL)
    assert (t.kp[s], t.ki[s]) == (0.4, 0.01)
    assert [row[5] for row in t.drain_changes()[1]] == ["adopted"]


@pytest.mark.parametrize("batched", [False, True])
def test_gains_adopted_outside_the_guards_bounds_are_said_so(batched):
    """No step of the tuner's leaves the guard's bounds: gains reported outside them are
    an operator's deliberate choice or samples that are not the DCS's; the audit says so."""
    t, s = table(ScalingAgent(1.2))
    ingest = ingest_one if batched else reference_ingest
    feed(t, s, [0.0])
    ingest(t, s, sample(1.0, kp=0.4, ki=0.01), WALL)
    ingest(t, s, sample(2.0, kp=5000.0, ki=0.01), WALL)
    details = [row[10] for row in t.drain_changes()[1]]
    assert details[0] == "gains reported by the gateway"
    assert details[1].startswith("gains reported by the gateway, OUTSIDE the guard's bounds")
    assert (t.kp[s], t.ki[s]) == (5000.0, 0.01)  # in force in the DCS: adopted all the same


@pytest.mark.parametrize("batched", [False, True])
def test_stale_gains_without_applied_seq_are_adopted_as_today(batched):
    t, s, ingest = _two_updates_ahead(batched)
    ingest(t, s, sample(331.0, kp=0.5, ki=0.01), WALL)  # not the gains just replaced
    assert (t.kp[s], t.ki[s]) == (0.5, 0.01) and not t.pending[s]
    gains, audit = t.drain_changes()
    assert gains == [(0.5, 0.01, 2, "LIC-101")] and [row[5] for row in audit] == ["adopted"]


@pytest.mark.parametrize("batched", [False, True])
@pytest.mark.parametrize("advisory", [False, True])
def test_applied_seq_equal_with_other_gains_is_an_operators_change(batched, advisory):
    t, s, ingest = _two_updates_ahead(batched)
    if advisory:  # advisory loops keep the rule without applied_seq: the gains just
        t.mode[s] = ADVISORY  # replaced (0.6) are an update in flight, even at seq 2
        ingest(t, s, sample(331.0, kp=0.6, ki=0.012, applied_seq=2), WALL)
        assert t.kp[s] == pytest.approx(0.72) and t.pending[s]
        return
    # 0.6 are the gains just replaced: without applied_seq they would count as in flight
    ingest(t, s, sample(331.0, kp=0.6, ki=0.012, applied_seq=2), WALL)
    assert (t.kp[s], t.ki[s]) == (0.6, 0.012) and not t.pending[s]
    gains, audit = t.drain_changes()
    assert gains == [(0.6, 0.012, 2, "LIC-101")] and [row[5] for row in audit] == ["adopted"]


@pytest.mark.parametrize("batched", [False, True])
def test_gains_reported_through_float32_are_not_an_operators_change(batched):
    t, s = table(ScalingAgent(1.2 + 1e-7))
    feed(t, s, [0.0, 165.0])
    step(t, np.array([s]), WALL)
    t.drain_changes()
    kp, ki = (float(np.float32(g)) for g in (t.kp[s], t.ki[s]))  # a float32 DCS
    assert kp != t.kp[s] and ki != t.ki[s]
    (ingest_one if batched else reference_ingest)(t, s, sample(166.0, kp=kp, ki=ki), WALL)
    assert not t.pending[s]  # the update arrived
    assert t.drain_changes() == ([], [])  # and nothing was adopted


@pytest.mark.parametrize(
    ("t_next", "kw", "reason"),
    [
        (10.0, {}, RejectReason.duplicate),
        (5.0, {}, RejectReason.out_of_order),
        (11.0, {"e": 1001.0}, RejectReason.out_of_range),  # 100 agent units of error
    ],
)
def test_rejected_samples_leave_the_loop_untouched(t_next, kw, reason):
    t, s = table()
    ingest_one(t, s, sample(10.0), WALL)
    before = _state_but_counters(t)
    with pytest.raises(Rejected) as info:
        ingest_one(t, s, sample(t_next, **kw), WALL)
    assert info.value.reason is reason
    assert _state_but_counters(t) == before
    assert t.n_rejected[s] == 1 and t.n_samples[s] == 1


def _state_but_counters(t: LoopTable) -> tuple[bytes, dict]:
    """The only loop's hidden state and runtime (integral, times, flags), counters aside."""
    ((_, hidden, runtime),) = t.snapshot()
    rt = orjson.loads(runtime)
    del rt["counters"]
    return hidden, rt


def test_flood_limit_per_loop_in_wall_time():
    t, s = table(rate=5.0)
    accepted = 0
    for i in range(20):
        try:
            ingest_one(t, s, sample(float(i)), WALL)  # all in the same wall instant
            accepted += 1
        except Rejected as exc:
            assert exc.reason is RejectReason.flood
    assert accepted == 5
    ingest_one(t, s, sample(100.0), WALL + 1.0)  # a second later there is room again


def test_reset_and_snapshot_restore():
    t, s = table()
    feed(t, s, [0.0, 165.0], [2.0, 2.0])
    step(t, np.array([s]), WALL)
    rows = t.snapshot()
    config = t.configs["LIC-101"]
    restored = LoopTable(untrained_agent(0), max_rate_hz=1e6)
    r = restored.add(config, kp=1.0, ki=0.02, seq=1, hidden=rows[0][1], runtime=rows[0][2], wall=0)
    np.testing.assert_array_equal(restored.hidden[r], t.hidden[s])
    for name in ("int_e", "last_t", "last_e", "next_due", "n_samples", "n_steps"):
        assert getattr(restored, name)[r] == getattr(t, name)[s], name

    result = t.reset("LIC-101", WALL)
    assert (t.kp[s], t.ki[s]) == (0.5, 0.01) and t.seq[s] == 2
    assert np.all(t.hidden[s] == 0) and t.int_e[s] == 0 and math.isnan(t.last_t[s])
    assert result.t[0] == 165.0 and t.status(s, WALL) is LoopStatus.waiting
    assert not ingest_one(t, s, sample(3.0), WALL)  # the time reference starts over


@pytest.mark.parametrize("batched", [False, True])
def test_a_resets_t_is_the_newest_sample_accepted_since_the_last_reset(batched):
    """docs/protocol.md (Gains): the plant time of the newest sample accepted since the
    registration or the last reset, 0.0 if there is none."""
    t, s = table()
    ingest = ingest_one if batched else reference_ingest
    assert t.reset("LIC-101", WALL).t[0] == 0.0  # nothing accepted since registration
    for ti in (10.0, 20.0):
        ingest(t, s, sample(ti), WALL)
    assert t.reset("LIC-101", WALL).t[0] == 20.0
    assert t.reset("LIC-101", WALL).t[0] == 0.0  # nothing accepted since the last reset
    ingest(t, s, sample(5.0), WALL)  # older than before the reset: accepted, the newest
    with contextlib.suppress(Rejected):
        ingest(t, s, sample(4.0), WALL)  # rejected: not counted
    assert t.reset("LIC-101", WALL).t[0] == 5.0
    audit = t.drain_changes()[1]
    assert [row[2] for row in audit] == [None, 20.0, None, 5.0]


@pytest.mark.parametrize("mode", ["auto", "advisory", "frozen"])
def test_a_reset_records_its_actor_in_the_audit_detail(mode):
    engine = TuningEngine(untrained_agent(0))
    engine.register(LoopConfig(**loop_body(mode=mode)), wall=WALL)
    engine.reset("LIC-101", wall=WALL, actor="alice@console")
    engine.reset("LIC-101", wall=WALL)  # no actor: the detail as before
    details = [row[-1] for row in engine.drain_changes()[1] if row[5] == "reset"]
    frozen = "agent state only: a frozen loop's gains are not published"
    if mode == "frozen":
        assert details == [f"{frozen}; actor=alice@console", frozen]
    elif mode == "advisory":
        assert details == [f"{PROPOSED}; actor=alice@console", PROPOSED]
    else:
        assert details == ["actor=alice@console", ""]


@pytest.mark.parametrize("batched", [False, True])
def test_a_far_future_sample_cannot_lock_the_loop_out(batched):
    """A poisoned timestamp (or a gateway restarted on a new clock) is re-anchored after
    CLOCK_RESET_SAMPLES consistent samples instead of rejecting the loop's data forever."""
    from service.engine.rules import CLOCK_RESET_SAMPLES

    t, s = table()
    assert feed(t, s, [0.0, 165.0]) == [165.0]
    ingest_one(t, s, sample(1e9), WALL)  # accepted: nothing tells it from a long outage
    rejected = []
    for k in range(CLOCK_RESET_SAMPLES):
        ti = 330.0 + 165.0 * k
        try:
            (ingest_one if batched else reference_ingest)(t, s, sample(ti), WALL)
        except Rejected as exc:
            rejected.append(exc.reason)
    assert rejected == [RejectReason.out_of_order] * (CLOCK_RESET_SAMPLES - 1)
    last = 330.0 + 165.0 * (CLOCK_RESET_SAMPLES - 1)
    assert t.last_t[s] == last  # re-anchored on the new clock, a fresh decimation window
    assert feed(t, s, [last + 165.0]) == [last + 165.0]
    # an isolated late sample is still rejected and does not start a run of its own
    with pytest.raises(Rejected):
        ingest_one(t, s, sample(10.0), WALL)
    assert t.back_n[s] == 1
    assert feed(t, s, [last + 330.0]) == [last + 330.0] and t.back_n[s] == 0


# -- excitation gate ------------------------------------------------------------------
def _gated(**guard) -> tuple[LoopTable, int]:
    """One sample per RL period (165 s); e_scale 0.1, so the smallest step is 2.0 by
    default, and the gate stays open 3 RL periods after a setpoint change."""
    return table(guard={"excitation_periods": 3.0, **guard})


def _due_at(t: LoopTable, s: int, setpoints, start: float = 0.0) -> list[int]:
    """Feed one sample per RL period with these setpoints (pv 50 on the first, then the
    setpoint before: a loop that follows within a period); indices that fell due."""
    pvs = [50.0, *setpoints[:-1]]
    return [
        k
        for k, (sp, pv) in enumerate(zip(setpoints, pvs, strict=True))
        if ingest_one(t, s, sample(start + 165.0 * k, e=None, sp=sp, pv=pv), WALL)
    ]


def test_excitation_gate_steps_only_after_a_setpoint_change():
    t, s = _gated()
    # steady at 50 for 6 periods: never due, each due period counted as quiet
    assert _due_at(t, s, [50.0] * 6) == []
    assert t.n_quiet[s] == 5 and t.n_steps[s] == 0
    assert t.status(s, WALL) == LoopStatus.quiet
    assert t.view("LIC-101", WALL).counters.quiet == 5
    # a 10 cm step (1 agent unit) at k = 6: due in the periods ending within 3 RL periods
    due = _due_at(t, s, [60.0] * 8, start=165.0 * 6)
    assert due == [0, 1, 2, 3]  # t = 990 (the step's own sample) ... 990 + 3 * 165
    assert t.status(s, WALL) == LoopStatus.quiet and t.n_quiet[s] == 5 + 4


def test_excitation_gate_ignores_small_steps_but_adds_up_a_ramp():
    t, s = _gated()
    assert _due_at(t, s, [50.0, 51.0, 50.0, 51.5, 50.5]) == []  # wiggles under 2.0
    # a ramp of 0.5 per period: a move each time it has moved 2.0 from the last one (52.0
    # at index 3, 54.0 at index 7); the agent is not stepped while it ramps (a change
    # every sample: units.ramp_gated), so those periods count as quiet
    ramp = 50.0 + 0.5 * np.arange(1, 9)
    quiet = t.n_quiet[s]
    assert _due_at(t, s, ramp.tolist(), start=165.0 * 5) == []
    assert t.move_t[s] == 165.0 * (5 + 7) and t.sp_ref[s] == 54.0
    assert t.excited_until[s] == 165.0 * (5 + 7 + 3) and t.n_quiet[s] == quiet + 8
    # a larger smallest step (agent units): the same ramp never counts
    t, s = _gated(excitation_min_step=0.5)
    assert _due_at(t, s, [50.0] + ramp[:5].tolist()) == [] and t.n_quiet[s] == 5


def test_excitation_gate_on_error_only_samples_and_off_switch():
    t, s = _gated()
    steady = [ingest_one(t, s, sample(165.0 * k, e=0.3), WALL) for k in range(4)]
    assert steady == [False] * 4
    # the error jumps by 10 (a setpoint change as an e-only gateway sees it)
    jumped = [ingest_one(t, s, sample(165.0 * k, e=10.3 - k), WALL) for k in range(4, 9)]
    assert jumped == [True, True, True, True, False]
    # gate off: every period due, status tuning
    t, s = table(guard={"excitation_periods": 0.0})
    assert _due_at(t, s, [50.0] * 4) == [1, 2, 3] and t.status(s, WALL) == LoopStatus.tuning


@pytest.mark.parametrize("batched", [False, True])
def test_the_gate_moves_with_a_new_plant_clock(batched):
    """A quiet loop whose gateway restarts its clock at 0 stays quiet (issue 18, 1); a
    loop whose window was open keeps what was left of it on the new clock."""
    from service.engine.rules import CLOCK_RESET_SAMPLES

    ingest = ingest_one if batched else reference_ingest
    t, s = _gated()
    # moved at 495: open to 990 (the PV follows within a period: a PV held off its setpoint
    # is an output at a limit, service.engine.output_limit)
    for k, sp in enumerate([50.0] * 3 + [60.0] + [60.0] * 6):
        ingest(t, s, sample(165.0 * k, e=None, sp=sp, pv=50.0 if k <= 3 else 60.0), WALL)
    assert t.status(s, WALL) == LoopStatus.quiet
    restarted = []
    for k in range(CLOCK_RESET_SAMPLES + 6):  # the new clock from 0, setpoint still
        try:
            restarted.append(ingest(t, s, sample(165.0 * k, e=None, sp=60.0, pv=60.0), WALL))
        except Rejected:
            restarted.append(None)
    assert restarted[: CLOCK_RESET_SAMPLES - 1] == [None] * (CLOCK_RESET_SAMPLES - 1)
    assert not any(restarted[CLOCK_RESET_SAMPLES - 1 :])  # never due: still quiet
    assert t.status(s, WALL) == LoopStatus.quiet

    t, s = _gated()
    for k, sp in enumerate([50.0, 60.0]):  # moved at 1165: open for 3 x 165 s
        ingest(t, s, sample(1000.0 + 165.0 * k, e=None, sp=sp, pv=50.0), WALL)
    for k in range(CLOCK_RESET_SAMPLES):
        with contextlib.suppress(Rejected):
            ingest(t, s, sample(10.0 * k, e=None, sp=60.0, pv=50.0), WALL)
    # re-anchored at t = 90 (old clock 1165): the 495 s left of the window end at 585
    assert t.excited_until[s] == pytest.approx(90.0 + 495.0)


def test_excitation_state_survives_a_snapshot():
    t, s = _gated()
    _due_at(t, s, [50.0, 50.0, 60.0])
    ((loop_id, hidden, runtime),) = t.snapshot()
    t2 = LoopTable(untrained_agent(0), max_rate_hz=1e6, capacity=2)
    config = t.configs[loop_id]
    s2 = t2.add(config, hidden=hidden, runtime=runtime, wall=WALL)
    assert (t2.sp_ref[s2], t2.excited_until[s2], t2.n_quiet[s2]) == (60.0, 330.0 + 495.0, 1)
    assert ingest_one(t2, s2, sample(495.0, e=None, sp=60.0, pv=50.0), WALL)  # still open
    # a snapshot from before the gate (no such keys, fewer counters) restores as closed
    old = orjson.loads(runtime)
    del old["sp_ref"], old["excited_until"]
    old["counters"] = old["counters"][:-1]
    t3 = LoopTable(untrained_agent(0), max_rate_hz=1e6, capacity=2)
    s3 = t3.add(config, hidden=hidden, runtime=orjson.dumps(old).decode(), wall=WALL)
    assert np.isnan(t3.sp_ref[s3]) and t3.excited_until[s3] == -math.inf


def test_status_counts_agree_with_each_loops_status():
    t = LoopTable(untrained_agent(0), max_rate_hz=1e6, capacity=2)
    gated = {"excitation_periods": 3.0}
    kinds = ["waiting", "frozen", "manual", "saturated", "quiet", "tuning", "stale", "gated"]
    for i, kind in enumerate(kinds * 2):
        mode = "frozen" if kind == "frozen" else "auto"
        guard = gated if kind in ("quiet", "gated") else {}
        body = loop_body(f"L{i}", sample_period_s=165.0, mode=mode, guard=guard)
        s = t.add(LoopConfig(**body), wall=WALL)
        if kind == "waiting":
            continue
        flags = {"auto": kind != "manual", "saturated": kind == "saturated"}
        wall = WALL if kind == "stale" else WALL + 1e3  # stale: no sample for 1,000 s
        for k in range(6):  # gated: a setpoint step in the last sample keeps it tuning
            sp = 60.0 if kind == "gated" and k == 5 else 50.0
            ingest_one(t, s, sample(165.0 * k, e=None, sp=sp, pv=50.0, **flags), wall)
    counts = t.status_counts(WALL + 1e3)
    singles = [t.status(s, WALL + 1e3) for s in t.slot_of.values()]
    assert counts == {status: singles.count(status) for status in LoopStatus}
    assert counts[LoopStatus.quiet] == 2 and counts[LoopStatus.tuning] == 4
    assert sum(counts.values()) == 16


@pytest.mark.parametrize("reference", [False, True])
def test_one_absurd_loop_never_breaks_the_step_of_the_others(reference):
    """Extreme but valid loops mixed into normal ones, all due at once (issue 18, 5):
    the normal loops are stepped, each extreme one stepped or left out as a fault."""
    rng = np.random.default_rng(5)
    precision = "reference" if reference else "float32"
    t = LoopTable(untrained_agent(0), max_rate_hz=1e6, capacity=4, inference_precision=precision)
    normal, extreme = [], []
    for i in range(40):
        if i % 3:
            body = loop_body(f"N{i}", sample_period_s=165.0, guard=GATE_OFF)
            normal.append(t.add(LoopConfig(**body), wall=WALL))
            continue
        # slow, high-gain hints put an engineering ki of 1e12 beyond 1e30 agent units
        hint = {k: float(10.0 ** rng.uniform(6, hi)) for k, hi in (("k_hat", 9), ("tau_hat", 8.5))}
        hint["pv_scale"] = float(10.0 ** rng.uniform(3, 9))
        body = loop_body(f"X{i}", sample_period_s=1e-3, scaling=hint, guard=GATE_OFF)
        extreme.append(t.add(LoopConfig(**body), wall=WALL))
    for s in normal + extreme:
        ingest_one(t, s, sample(0.0, e=0.0), WALL)
        gains = {} if s in normal else {"kp": 10.0 ** rng.uniform(-12, 12), "ki": 1e12}
        e = 1.0 if s in normal else float(rng.uniform(-1e-6, 1e-6))
        t.period[s] = 1.0  # everyone due at the next sample
        ingest_one(t, s, sample(2.0, e=e, **gains), WALL)
    # and numbers no sample can bring, however they came about
    absurd = extreme[:3]
    t.ki[absurd[0]], t.int_e[absurd[1]], t.obs_e[absurd[2]] = 1e300, np.inf, np.nan
    result = step(t, np.array(normal + extreme), WALL)
    stepped = {t.slot_of[i] for i in result.loop_ids}
    assert set(normal) <= stepped
    assert np.isfinite(result.new).all() and (result.new > 0).all()
    faulted = set(extreme) - stepped
    assert set(absurd) <= faulted
    assert all(t.n_faults[s] == 1 and t.n_steps[s] == 0 for s in faulted)
    assert all(t.n_faults[s] == 0 for s in stepped)
    assert np.isfinite(t.hidden[list(stepped)]).all()


@pytest.mark.parametrize("batched", [False, True])
def test_the_agents_error_is_the_mean_over_the_end_of_the_period(batched):
    """docs/tuner.md, Robustness measures 5: e = the mean error of the samples at
    due - 0.2 period <= t < due, or the sample at due where the setpoint moved inside."""
    t, s = table(sample_period_s=1.0)
    ingest = ingest_one if batched else reference_ingest
    assert t.period[s] == 165.0 and t.e_scale[s] == 0.1  # the two-tank scaling
    errors = np.random.default_rng(0).normal(scale=0.1, size=331)
    sps = np.where(np.arange(331) < 300, 0.0, 5.0)  # a move at 300 s, in the second window
    obs = {}
    for k in range(331):
        if ingest(t, s, sample(float(k), e=float(errors[k]), sp=float(sps[k])), WALL):
            obs[k] = float(t.obs_e[s])
    assert sorted(obs) == [165, 330]
    # 165 - 33 <= t < 165: the 33 samples 132..164, in agent units
    assert obs[165] == pytest.approx(0.1 * errors[132:165].mean(), rel=1e-12)
    assert obs[330] == pytest.approx(0.1 * errors[330], rel=1e-12)  # moved at 300 s
