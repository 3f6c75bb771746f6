"""A controller output held at a limit, seen in the data (service/engine/output_limit.py):
closed FOPTD loops under a clamped PI, through the engine, with the gateway's saturated
flag never set."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch
from service.engine import LoopConfig, TuningEngine, output_limit
from service.learn.verification import StillAgent

pytestmark = pytest.mark.timeout(120)
K, TAU, THETA = 1.0, 8.0, 1.0
"""The plant: PV units per output unit, s, s (sampled every second)."""


class Loop:
    """One loop: plant, DCS PI (output limits, executing every ``every`` samples), gateway
    (reports op as the DCS holds it, rounded to ``quantum`` when given) and engine."""

    def __init__(
        self, *, u_max=np.inf, noise=0.0, every=1, quantum=0.0, send_op=True, seed=0,
        k=K, tau=TAU, theta=THETA, kp=1.0, ki=0.1,
    ):  # fmt: skip
        self.engine = TuningEngine(StillAgent())
        # gate off: stepped every RL period (44 s) whatever the setpoint does; the hint is
        # the model's constants (the plant's unless k, tau or theta say otherwise)
        self.engine.register(LoopConfig(
            id="V", kp=kp, ki=ki, sample_period_s=1.0,
            scaling={"k_hat": K, "tau_hat": TAU, "pv_scale": 1.0},
            guard={"excitation_periods": 0.0},
        ), wall=0.0)  # fmt: skip
        self.plant = FOPTDBatch(k, tau, theta, dt=1.0, noise_std=noise, seed=seed,
                                max_theta=max(theta, 1.0))  # fmt: skip
        self.plant.reset(1.0)
        self.pi = PIBatch(kp, ki, dt=1.0, n=1, u_min=0.0, u_max=u_max)
        self.pi.initialise([1.0 / k])
        self.u = 1.0 / k
        self.load = 0.0
        """A disturbance at the plant's input (output units)."""
        self.every, self.quantum, self.send_op = every, quantum, send_op
        self.t = 0
        self.rows: list = []

    def run(self, sp: float, n: int) -> list[str]:
        """``n`` samples at setpoint ``sp``; each sample's status."""
        seen = []
        for _ in range(n):
            pv = float(self.plant.measure()[0])
            if self.t % self.every == 0:
                self.u = float(self.pi.step([sp - pv])[0])
            sample = {"loop_id": "V", "t": float(self.t), "sp": sp, "pv": pv,
                      "kp": float(self.pi.kp[0]), "ki": float(self.pi.ki[0])}  # fmt: skip
            if self.send_op:
                q = self.quantum
                sample["op"] = round(self.u / q) * q if q else self.u
            for update in self.engine.ingest([sample], wall=float(self.t)):
                self.pi.set_gains(update.kp, update.ki)  # the DCS applies the tuner's gains
            self.plant.step([self.u + self.load])
            self.t += 1
            seen.append(self.engine.view("V", wall=float(self.t)).status.value)
        self.rows += self.engine.drain_changes()[1]
        return seen

    def restart(self) -> TuningEngine:
        """A new engine restored from this one's snapshot of the loop (a daemon's restart),
        in its place."""
        ((_, hidden, runtime),) = self.engine.snapshot(["V"])
        other = TuningEngine(StillAgent())
        other.restore(self.engine.table.configs["V"], kp=1.0, ki=0.1, seq=0, hidden=hidden,
                      runtime=runtime, wall=0.0)  # fmt: skip
        self.engine = other
        return other

    @property
    def steps(self) -> int:
        return self.engine.view("V", wall=0.0).counters.steps


def test_an_output_held_at_its_limit_pauses_tuning_as_saturated_until_it_moves():
    loop = Loop(u_max=1.5)
    assert set(loop.run(1.0, 500)) == {"tuning"}
    before = loop.steps
    assert before >= 10  # stepped every RL period
    # the move asks for an output of 2: the DCS clamps it at 1.5, the PV stops at 1.5
    seen = loop.run(2.0, 300)
    held_at = seen.index("saturated")
    # 20 samples at the limit at least, and the law's change built up by then
    assert output_limit.HELD_SAMPLES <= held_at <= 40
    assert set(seen[held_at:]) == {"saturated"}
    view, perf = loop.engine.view("V", wall=0.0), loop.engine.performance("V")
    assert view.counters.output_holds == 1 and perf.window.output_held == 1.5
    # no RL step while held (one at most before it: 40 s, under an RL period)
    assert loop.steps <= before + 1
    held_steps = loop.steps
    (row,) = [r for r in loop.rows if r[5] == "output_held"]
    detail = json.loads(row[10])
    assert detail["op"] == 1.5 and detail["samples"] >= output_limit.HELD_SAMPLES
    assert detail["law_change"] >= output_limit.HELD_SHARE * 1.5
    # back to the old setpoint: the output leaves the limit at once, tuning resumes
    seen = loop.run(1.0, 500)
    assert seen[0] == "tuning" and set(seen) == {"tuning"}
    assert loop.engine.performance("V").window.output_held is None
    assert loop.steps >= held_steps + 10
    assert loop.engine.view("V", wall=0.0).counters.output_holds == 1


def test_a_held_output_survives_a_snapshot_and_restore():
    loop = Loop(u_max=1.5)
    loop.run(1.0, 100)
    assert loop.run(2.0, 100)[-1] == "saturated"
    other = loop.restart()
    assert loop.run(2.0, 1) == ["saturated"]  # held from the first sample after it
    assert other.view("V", wall=0.0).counters.output_holds == 1


def test_the_gateways_flag_governs():
    loop = Loop(u_max=1.5)
    loop.run(1.0, 100)
    seen = []  # the gateway says so: saturated, and no hold of the data's
    for _ in range(100):
        pv = float(loop.plant.measure()[0])
        loop.u = float(loop.pi.step([2.0 - pv])[0])
        loop.engine.ingest([{"loop_id": "V", "t": float(loop.t), "sp": 2.0, "pv": pv,
                             "op": loop.u, "saturated": bool(loop.pi.saturated[0])}],
                           wall=float(loop.t))  # fmt: skip
        loop.plant.step([loop.u])
        loop.t += 1
        seen.append(loop.engine.view("V", wall=float(loop.t)).status.value)
    assert seen[-1] == "saturated"
    assert loop.engine.view("V", wall=0.0).counters.output_holds == 0


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_without_op_a_pv_that_does_not_follow_the_law_is_held(noise):
    """No op in the samples (the output reconstructed from the PI law): the move asks the
    output for 2, the valve stops at 1.5, the PV at 1.5. The PV rule holds the loop from
    the second block (60 s: the envelope's longest lag, no model) whose PV did not follow
    the law's push, the third of the run; back at 1.0 the run ends and tuning resumes."""
    loop = Loop(u_max=1.5, send_op=False, noise=noise)
    assert set(loop.run(1.0, 500)) == {"tuning"}
    seen = loop.run(2.0, 400)
    block = output_limit.BLOCK * 2.0 * TAU  # the hint's time unit: 2 tau_hat
    held_at = seen.index("saturated")
    assert (output_limit.STALLS + 1) * block <= held_at + 1 <= (output_limit.STALLS + 2) * block
    assert set(seen[held_at:]) == {"saturated"}
    (row,) = [r for r in loop.rows if r[5] == "output_held"]
    detail = json.loads(row[10])
    assert detail["seen"] == "pv" and detail["block_s"] == pytest.approx(block)
    assert detail["error"] == pytest.approx(0.5, abs=0.05)  # the PV stands at the limit
    assert detail["moved_pv"] < output_limit.FOLLOW * detail["expected_pv"]
    window = loop.engine.performance("V").window
    assert window.pv_stalled and window.output_held is None  # (no op to show)
    held_steps = loop.steps
    assert loop.run(2.0, 200)[-1] == "saturated" and loop.steps <= held_steps + 1
    assert set(loop.run(1.0, 300)) == {"tuning"}  # the error's sign turns: the run ends
    assert not loop.engine.performance("V").window.pv_stalled
    assert loop.steps >= held_steps + 5
    assert loop.engine.view("V", wall=0.0).counters.output_holds == 1


def test_a_stalled_pv_survives_a_snapshot_and_restore():
    loop = Loop(u_max=1.5, send_op=False)
    loop.run(1.0, 100)
    assert loop.run(2.0, 250)[-1] == "saturated"
    other = loop.restart()
    assert loop.run(2.0, 1) == ["saturated"]  # held from the first sample after it
    assert other.performance("V").window.pv_stalled
    assert other.view("V", wall=0.0).counters.output_holds == 1


@pytest.mark.parametrize(
    ("case", "kw"),
    [
        ("as tuned", {}),
        ("noise", {"noise": 0.1}),
        ("K a third of the hint's", {"k": K / 3.0}),  # the envelope's lowest gain
        ("lag at the envelope's edge", {"tau": 1.5 * TAU, "theta": 1.5 * 1.5 * TAU}),
        ("load steps", {}),
    ],
)
def test_a_linear_loop_without_op_is_never_held(case, kw):
    """A PV that follows the law, however slowly and whatever the disturbances, inside
    the envelope the rule assumes: no hold. The PI is tuned 10-20x too slow (kp 0.1, ki
    0.005 per s: most plant loops are), so the error outlasts the rule's blocks and the
    blocks are judged (at least 4, the PV moving well beyond what the rule asks); setpoint
    moves up and down of 0.2-1, load steps of 0.5 at the plant's input."""
    judged = []
    judge = output_limit._pv_rule

    def spy(tb, slots, cols, *args):
        before = tb.ps_prev[slots].copy()
        held = judge(tb, slots, cols, *args)
        judged.extend(~np.isnan(before) & (tb.ps_prev[slots] != before))
        return held

    loop = Loop(send_op=False, seed=2, kp=0.1, ki=0.005, **kw)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(output_limit, "_pv_rule", spy)
        seen = []
        for sp in (1.0, 2.0, 1.5, 0.8, 1.0, 1.2, 1.0):
            seen += loop.run(sp, 600)
        if case == "load steps":
            for load in (0.5, -0.5, 0.0, 0.5, 0.0):
                loop.load = load
                seen += loop.run(1.0, 600)
    assert sum(judged) >= 4
    assert "saturated" not in seen
    assert loop.engine.view("V", wall=0.0).counters.output_holds == 0


@pytest.mark.parametrize(
    ("noise", "every", "quantum"),
    [
        (0.0, 1, 0.0),  # noise-free: a converged loop's output barely moves, nor its law
        (0.01, 1, 0.0),  # 1 % noise
        (0.01, 4, 0.0),  # the gateway samples 4 times per execution of the DCS's PI
        (0.0, 1, 0.02),  # op reported in steps of 0.02 (1.5 % of its range, 2.5 % of it)
        (0.01, 1, 0.02),
    ],
)
def test_an_output_the_pi_moves_is_never_held(noise, every, quantum):
    loop = Loop(noise=noise, every=every, quantum=quantum, seed=1)
    seen = []
    for sp in (1.0, 1.3, 0.8, 1.0, 1.05, 1.0):
        seen += loop.run(sp, 250)
    seen += loop.run(1.0, 1000)  # a long quiet stretch: converged
    assert "saturated" not in seen
    assert loop.engine.view("V", wall=0.0).counters.output_holds == 0
    assert loop.steps >= 40  # tuned all along (the hint check's model tuning holds a while)


def test_a_loop_without_a_model_is_not_identified_from_a_response_at_the_limit():
    loop = Loop(u_max=1.5)
    loop.engine = TuningEngine(StillAgent())
    loop.engine.register(LoopConfig(id="V", kp=1.0, ki=0.1, sample_period_s=1.0), wall=0.0)
    loop.run(1.0, 100)
    assert set(loop.run(2.0, 200)) == {"identifying"}  # before saturated, in precedence
    ident = loop.engine.view("V", wall=float(loop.t)).identification
    assert ident.why == "segment ended: output saturated" and ident.model is None
    assert [r[5] for r in loop.rows] == ["output_held"]
