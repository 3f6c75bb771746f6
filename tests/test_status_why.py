"""Every status but ``tuning`` says in the loop's view what holds the loop, with the
numbers, and the operator's next step (``status_why``): each status driven through
:class:`TuningEngine` with real samples (a simulated loop for the hint checks)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine, box, model_use
from service.engine.identify import Model
from service.wire.protocol import LoopStatus
from tests.test_identify import H, K, drive, hinted

pytestmark = pytest.mark.timeout(120)
SCALING = {"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0}


def _loop(**over) -> LoopConfig:
    body = {"id": "L", "kp": 0.5, "ki": 0.01, "sample_period_s": 1.0, "scaling": SCALING,
            "guard": {"identify": False}, **over}  # fmt: skip
    return LoopConfig.model_validate(body)


def _sample(t: float, **over) -> dict:
    return {"loop_id": "L", "t": t, "sp": 50.0, "pv": 50.0, "kp": 0.5, "ki": 0.01,
            "auto": True, "saturated": False, **over}  # fmt: skip


def _factor(why: str, what: str) -> float:
    """The ``(N x)`` the why gives after the scaling in force's ``what`` (K or tau)."""
    return float(
        re.search(rf"against the scaling in force's.*?{what} = [^(]*\(([0-9.e+-]+)x\)", why)[1]
    )


def test_a_hint_off_beyond_the_tolerance_says_by_how_much_and_what_to_do():
    """k_hat 2.5x the plant's K: flagged hint_mismatch (tolerance 2x), tuning goes on;
    the why gives the identified K against the hint's and the next step."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(k_hat=2.5 * K), wall=0.0)
    drive(engine, moves=6)
    view = engine.view("L", wall=349.0)
    assert view.status == LoopStatus.hint_mismatch
    why = view.status_why
    assert why.startswith("the identified model disagrees with the scaling in force")
    assert "guard.hint_tolerance (2x)" in why
    assert _factor(why, "K") == pytest.approx(1 / 2.5, rel=0.25)
    assert _factor(why, "tau") == pytest.approx(1.0, rel=0.3)
    assert "Next: PATCH guard.auto_rescale true" in why and "k_hat and tau_hat" in why


def test_a_hint_so_far_off_the_loop_leaves_the_envelope_says_where_and_what_to_do():
    """k_hat 4x the plant's K: the model appears at gain 0.125, below the envelope's
    0.167: out_of_envelope (tuning pauses); the why gives the envelope, where the model
    lies in it, the hint's factor, and the rescale as the next step (the hint mismatches)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(k_hat=4.0 * K), wall=0.0)
    drive(engine, moves=6)
    view = engine.view("L", wall=349.0)
    assert view.status == LoopStatus.out_of_envelope and view.identification.why == ""
    why = view.status_why
    assert (
        "outside the agent's envelope (gain 0.1667..1.5, tau 0.1667..1.5, theta/tau up to 1.5)"
        in why
    )
    place = re.search(r"in the agent's units: gain ([0-9.e+-]+) \(([0-9.e+-]+) % beyond", why)
    gain = float(place[1])
    assert gain == pytest.approx(0.5 / 4, rel=0.25) and gain < 0.5 / 1.5 / 2
    assert float(place[2]) == pytest.approx(100 * (1 - gain * 1.5 / 0.25), abs=0.5)
    assert "resumes when a confident model lies within gain 0.1833..1.364, tau 0.1833" in why
    assert _factor(why, "K") == pytest.approx(1 / 4, rel=0.25)
    assert (
        "Next: the hint is off: PATCH guard.auto_rescale true" in why
        and "POST /loops/{id}/identify" in why
    )


def test_a_loop_paused_inside_the_hysteresis_band_says_what_resumes_it():
    """A model at apparent tau 0.1658 (19.9 s on a 60 s hint) pauses the loop; the next
    at 0.1792 (21.5 s) is back inside the envelope but not within the resume edge
    0.1833: still paused, and the why says so with that edge (it said "outside the
    agent's envelope (... tau 0.167..1.5 ...)" and "tau 0.179", inside that range)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(LoopConfig(id="C", kp=0.125, ki=0.003125, sample_period_s=1.0,
                               scaling={"k_hat": 2.0, "tau_hat": 60.0, "pv_scale": 1.0},
                               guard={"auto_rescale": False}), wall=0.0)  # fmt: skip
    engine.ingest([{"loop_id": "C", "t": 0.0, "sp": 1.0, "pv": 0.0, "kp": 0.125,
                    "ki": 0.003125}], wall=0.0)  # fmt: skip
    tb = engine.table
    s = tb.slot("C")
    why = []
    for t, tau in [(1.0, 19.9), (2.0, 21.5)]:
        m = Model(k=2.0, tau=tau, theta=4.0, noise=0.01, move=2.0, r2=0.999, k_rse=0.005,
                  tau_rse=0.005, events=4, confident=True)  # fmt: skip
        tb.ident[s].model = m
        model_use.use(tb, s, m, t, t)
        view = engine.view("C", wall=t)
        assert view.status == LoopStatus.out_of_envelope
        why.append(view.status_why)
    assert "tau 0.1658 (0.5 % beyond the envelope's edge 0.1667)" in why[0]
    assert "tau 0.1792 (inside the envelope, beyond the resume edge 0.1833)" in why[1]
    assert "gain 0.5, " in why[1] and "theta/tau 0.186" in why[1]
    assert "It resumes when a confident model lies within gain 0.1833..1.364, tau " in why[1]


class _Watched(TuningEngine):
    """An engine that keeps, after each sample, loop L's view while it is paused out of
    the envelope, and its envelope audit rows."""

    def __init__(self) -> None:
        super().__init__(untrained_agent(0))
        self.paused, self.rows = [], []

    def ingest(self, samples, *, wall=None):
        out = super().ingest(samples, wall=wall)
        self.rows += [r for r in self.drain_changes()[1] if r[5].endswith("_envelope")]
        view = self.view("L", wall=wall)
        if view.status == LoopStatus.out_of_envelope:
            self.paused.append(view)
        return out


def test_a_paused_loop_names_the_model_that_paused_it_not_a_later_one():
    """A hint 4x off the plant's K pauses the loop (a model at gain 0.126, t = 600 s);
    then the plant's K moves to the hint's and the models of data that mix both plants
    are unconfident: some put gain and tau inside the resume edges (0.45, 0.59 at t =
    2296 s), some look integrating. The why gave the latest model alone ("a model
    identified outside the agent's envelope (gain 0.1667..1.5, ...) paused tuning; the
    latest model in the agent's units: gain 0.4498, tau 0.5866, ...", and at t = 1664 s
    "the process looks integrating" of a loop no integrator paused): it names the one
    that paused the loop, as its audit row, and the latest as differing, also after a
    restart (the snapshot keeps it)."""
    engine = _Watched()
    engine.register(hinted(k_hat=4.0 * K), wall=0.0)
    drive(engine, moves=6)
    paused_at = engine.view("L", wall=0.0).last_sample_t
    ((_, hidden, runtime),) = engine.snapshot()
    drive(engine, moves=8, k=4.0 * K, t0=paused_at + H, seed=1)
    (out, back) = engine.rows  # resumed by the confident models of the plant now
    assert (out[5], back[5]) == ("out_of_envelope", "in_envelope")
    app, when = json.loads(out[10]), out[2]
    named = (
        f"the model identified at t = {when:.10g} s (plant time) outside the agent's "
        f"envelope (gain 0.1667..1.5, tau 0.1667..1.5, theta/tau up to 1.5) paused tuning; "
        f"in the agent's units: gain {app['gain']:.4g} ("
    )
    assert app["gain"] == pytest.approx(0.5 / 4, rel=0.05)
    assert all(v.status_why.startswith(named) for v in engine.paused)
    resume = box.edges(box.RESUME_MARGIN)

    def inside(a: dict) -> bool:
        return all(resume[k][0] <= a[k] <= resume[k][1] for k in ("gain", "tau"))

    later = [v for v in engine.paused if v.identification.model is not None
             and v.identification.apparent != app]  # fmt: skip
    within = [v for v in later if not v.identification.model.integrating
              and inside(v.identification.apparent)]  # fmt: skip
    assert within and all(not v.identification.model.confident for v in within)
    for v in within:
        a = v.identification.apparent
        assert f"; the latest model differs: gain {a['gain']:.4g}, tau {a['tau']:.4g}" in (
            v.status_why
        )
        assert "(not confident). It resumes when" in v.status_why
    integrating = [v for v in later if v.identification.model.integrating]
    assert integrating and all(
        "; the latest model differs: integrating, K = " in v.status_why for v in integrating
    )
    # restored from the snapshot taken while paused: the same model named
    again = TuningEngine(untrained_agent(0))
    kp, ki = engine.paused[0].kp, engine.paused[0].ki
    again.restore(hinted(k_hat=4.0 * K), kp=kp, ki=ki, seq=0, hidden=hidden, runtime=runtime,
                  wall=0.0)  # fmt: skip
    again.ingest([{"loop_id": "L", "t": paused_at + H, "sp": 50.0, "pv": 50.0, "kp": kp,
                   "ki": ki}], wall=1.0)  # fmt: skip
    view = again.view("L", wall=1.0)
    assert view.status == LoopStatus.out_of_envelope and view.status_why.startswith(named)


def test_the_other_statuses_say_why_with_their_numbers():
    engine = TuningEngine(untrained_agent(0))

    def one(config: LoopConfig, samples: list[dict], wall: float) -> tuple[LoopStatus, str]:
        engine.register(config, wall=0.0)
        for s in samples:
            engine.ingest([s], wall=s["t"])
        view = engine.view("L", wall=wall)
        engine.remove("L")
        return view.status, view.status_why

    st, why = one(_loop(), [], 0.0)
    assert st == LoopStatus.waiting and why.startswith("no sample received")
    st, why = one(_loop(mode="frozen"), [_sample(0.0)], 0.0)
    assert st == LoopStatus.frozen and "PATCH mode auto" in why
    st, why = one(_loop(), [_sample(0.0)], 100.0)
    assert st == LoopStatus.stale and why.startswith("no sample for 100 s, more than ")
    assert "(5 s)" in why  # guard.stale_periods 5 x 1 s
    engine.register(_loop(), wall=0.0)  # restored after a restart: no sample since
    engine.ingest([_sample(0.0)], wall=0.0)
    ((_, hidden, runtime),) = engine.snapshot()
    engine.remove("L")
    engine.restore(_loop(), kp=0.5, ki=0.01, seq=0, hidden=hidden, runtime=runtime, wall=9.0)
    view = engine.view("L", wall=10.0)
    engine.remove("L")
    assert view.status == LoopStatus.stale
    assert view.status_why.startswith("no sample since the tuner started, more than ")
    st, why = one(_loop(), [_sample(0.0, kp=100.0)], 0.0)
    assert st == LoopStatus.gains_out_of_bounds
    assert why.startswith(
        "the gateway reports kp = 100, ki = 0.01, outside the guard's bounds (kp "
    )
    st, why = one(_loop(scaling=None, guard={}), [_sample(0.0)], 0.0)
    assert st == LoopStatus.identifying and "move the setpoint in auto" in why
    st, why = one(_loop(), [_sample(float(t), auto=t < 5) for t in range(10)], 9.0)
    assert st == LoopStatus.manual and "in manual (" in why and "back in auto" in why
    st, why = one(_loop(), [_sample(0.0, saturated=True)], 0.0)
    assert st == LoopStatus.saturated and why.startswith("the gateway reports the output saturated")
    quiet = _loop(guard={"identify": False, "excitation_periods": 2.0})
    st, why = one(quiet, [_sample(float(t)) for t in range(0, 400, 5)], 395.0)
    assert st == LoopStatus.quiet
    assert "guard.excitation_periods (2) RL periods (330 s)" in why  # RL period 165 s
    st, why = one(_loop(guard={"identify": False, "excitation_periods": 0.0}),
                  [_sample(0.0)], 0.0)  # fmt: skip
    assert st == LoopStatus.tuning and why is None


def test_a_loop_quiet_under_the_noise_rule_names_the_noise_threshold():
    """Setpoint moves of 3 pv units clear guard.excitation_min_step (0.2 pv_scales = 2)
    but not 5 x the noise sigma (about 1): the why names the noise rule's threshold
    (it blamed excitation_min_step, which the moves cleared)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(_loop(guard={"identify": False, "excitation_periods": 2.0}), wall=0.0)
    noise = np.random.default_rng(0).normal(0.0, 1.0, 400)
    for t in range(400):
        sp = 50.0 + 3.0 * ((t // 100) % 2)
        engine.ingest([_sample(float(t), sp=sp, pv=sp + noise[t])], wall=float(t))
    view = engine.view("L", wall=399.0)
    assert view.status == LoopStatus.quiet
    why = view.status_why
    step, sigma = re.search(
        r"at least ([0-9.]+) \(pv units\): 5 x the measured noise sigma \(([0-9.]+)\)", why
    ).groups()
    assert float(step) == pytest.approx(5.0 * float(sigma), rel=0.01)
    assert float(sigma) == pytest.approx(1.0, rel=0.2)
    assert "more than guard.excitation_min_step (0.2 pv_scales = 2 in pv units)" in why
    assert "Next: move the setpoint by that much, reduce the measurement noise" in why


def test_the_envelope_guard_switched_off_resumes_a_loop_it_paused():
    """``PATCH guard.envelope_guard false`` on a paused loop: with the guard off no model
    is judged against the envelope, so before the fix nothing resumed it and the agent
    never stepped again (0 steps over eight more moves); now the agent steps again, once
    the cool-down after the model's tuning the pause put in force is over."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hinted(k_hat=4.0 * K), wall=0.0)
    drive(engine, moves=6)
    assert engine.view("L", wall=349.0).status == LoopStatus.out_of_envelope
    engine.reconfigure(hinted(k_hat=4.0 * K, envelope_guard=False))
    view = engine.view("L", wall=349.0)
    assert view.status != LoopStatus.out_of_envelope
    assert "envelope" not in (view.status_why or "")
    before = view.counters.steps
    drive(engine, moves=8, t0=view.last_sample_t + H, seed=1)
    # the agent is stepped again (this untrained one's steps the model check may hold)
    assert engine.view("L", wall=349.0).counters.steps >= before + 3
