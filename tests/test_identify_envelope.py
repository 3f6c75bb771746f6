"""Issue 13's envelope-guard bar on a drifting plant: a plant whose time constant ramps to
5x during tuning gets paused before its step-test MSE exceeds 3x its best.

One hint-free loop, identified and tuned by the shipped agent for 14 setpoint moves, then
its time constant ramps continuously (every sample) from tau0 toward 5 tau0 at
:data:`DRIFT_RATE`. At every change of the gains and every fifth sample, the step-test
MSE of the gains in force is taken on the plant as it is then (the paper's step test, in
the agent units of the initial plant: K and tau0 appear as 0.5); "its best" is the
lowest so far.

Measured (docs/identification.md, The envelope guard, with the table of rates): the loop
is paused at 3.4 tau0 (the envelope's edge is 3 tau0), its MSE before the ramp stays at
1.0x its best, and on the ramp the gains follow the drifting plant's models
(``model_check.follow``: 74x at most before the pause, 22x at it; 1,760x at most with the
gains held on the first model's tuning). The 3x line is **missed** on every ramp
measured: near its optimum the step test is so sharp that the best gains pass 3x their
MSE after a 5 % rise of tau (asserted below), which is within identification's error."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import step_test_mse
from plant_sim.pi import PIBatch
from service.agent import DEFAULT_WEIGHTS, load_agent
from service.engine import LoopConfig, TuningEngine
from service.engine.box import ENVELOPE_MARGIN, TRAINING_BOX
from service.engine.first_tuning import model_gains
from tests.test_identify import gains

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent"),
]

K, TAU, THETA, H = 2.0, 40.0, 10.0, 4.0
NOISE, SIZE = 0.5, 20.0
SETTLE_MOVES, EVERY = 14, 6.0
"""Moves before the ramp (identification and tuning); a move every EVERY time constants
of the plant as it is."""
DRIFT_RATE = 0.02
"""Growth of tau per EVERY tau0 of plant time, in tau0 (continuous). Moves come every
EVERY tau of the plant as it is, so tau grows by 2 % of itself between two moves: 5x in
1,200 tau0 (13 h for this loop's 40 s). Drift in a real plant (fouling, wear, a valve's
characteristic) is slower still, hours to months for such a loop; 2 % is the slowest ramp
this test affords (about 8,000 samples to the pause). Slower and faster rates:
``python -m tests.test_identify_envelope RATE...`` (docs/identification.md)."""
BATCH = 4
"""Samples per ``ingest`` call: gains apply up to 3 samples late (an RL period is about 55
samples here), for a quarter of the engine's per-call cost."""
EDGE = 2 * TRAINING_BOX["tau"][1] * ENVELOPE_MARGIN
"""The plant's tau (in tau0) at which the loop leaves the envelope: apparent tau 1.5."""


def agent_mse(kp, ki, tau):
    """The step-test MSE of engineering gains on the plant with time constant ``tau``, in
    the agent units of the initial plant (arrays: one test each)."""
    kp_a, ki_a = np.asarray(kp) * K / 0.5, np.asarray(ki) * K / 0.5 * TAU / 0.5
    return step_test_mse(0.5, 0.5 * np.asarray(tau) / TAU, 0.5 * THETA / TAU, kp_a, ki_a)


def drift(rate: float, *, after_pause: int = 50) -> dict:
    """The loop through its settling moves and a ramp at ``rate`` (None: the instantaneous
    case, +tau0/4 at each move), until ``after_pause`` samples after the pause."""
    started = time.perf_counter()
    engine = TuningEngine(load_agent())
    kp, ki = gains()
    engine.register(LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H), wall=0.0)
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=NOISE, seed=0)
    plant.reset(50.0)
    pi = PIBatch(kp, ki * H, dt=1.0)
    pi.initialise(50.0 / K)
    rng = np.random.default_rng(1)
    tb = engine.table
    s = tb.slot("L")
    sp, tau, j, moves, next_move = 50.0, TAU, 0, 0, int(EVERY * TAU / H)
    ramp_j = paused_j = None
    stop = np.inf  # set at the pause (or 2,000 samples after the ramp's end: no pause)
    rows, batch, audit = [], [], []  # rows: (kp, ki, tau, identified) of each sample
    while j < stop:
        if j == next_move:
            moves += 1
            sp = 50.0 + SIZE * (1 if moves % 2 else -1) * rng.uniform(0.5, 1.0)
            next_move = j + int(EVERY * tau / H)
            if moves == SETTLE_MOVES + 1:
                ramp_j = j
            if rate is None and ramp_j is not None:
                tau = min(5.0 * TAU, tau + TAU / 4)
        if rate is not None and ramp_j is not None:
            tau = min(5.0 * TAU, TAU * (1.0 + rate * (j - ramp_j) * H / (EVERY * TAU)))
        plant.set_params(tau=tau / H)
        y = float(plant.measure()[0])
        batch.append({"loop_id": "L", "t": j * H, "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                      "ki": float(pi.ki[0] / H)})  # fmt: skip
        u = pi.step(sp - y)  # with the gains the sample reports; updates for the next
        if len(batch) == BATCH:
            for up in engine.ingest(batch, wall=float(j)):
                pi.set_gains(up.kp, up.ki * H)
            batch = []
            audit += engine.drain_changes()[1]
            if tb.out_env[s] and paused_j is None:
                paused_j, stop = j, j + after_pause
        if tau == 5.0 * TAU and stop == np.inf:
            stop = j + 2000
        rows.append((float(pi.kp[0]), float(pi.ki[0] / H), tau, bool(tb.n_identified[s])))
        plant.step(u)
        j += 1
    out = {"wall_s": time.perf_counter() - started, "samples": j}
    out["view"] = engine.view("L", wall=float(j))
    follows = [r[2] for r in audit if r[5] == "model" and '"after":"followed"' in r[10]]
    out["followed"] = len(follows)
    out["followed_before_ramp"] = sum(t < ramp_j * H for t in follows)
    out["rollbacks"] = sum(r[5] == "rollback" for r in audit)
    a = np.array(rows)
    # the MSE wherever the gains changed and every 5th sample (tau moves every sample)
    last = j - 1 if paused_j is None else paused_j
    idx = np.flatnonzero(a[:, 3] > 0)
    idx = idx[idx <= last]
    changed = np.r_[True, (np.diff(a[idx, :2], axis=0) != 0).any(axis=1)]
    idx = idx[changed | (idx % 5 == 0) | (idx == last)]
    parts = np.array_split(idx, idx.size // 400 + 1)
    mse = np.concatenate([agent_mse(*a[part, :3].T) for part in parts])
    ratio = mse / np.minimum.accumulate(mse)
    on_ramp = idx >= ramp_j
    out["paused_at"] = None if paused_j is None else float(a[paused_j, 2] / TAU)
    out["before_ramp"] = float(ratio[~on_ramp].max())
    out["on_ramp"] = float(ratio[on_ramp].max())
    out["on_ramp_at"] = float(a[idx[on_ramp][np.argmax(ratio[on_ramp])], 2] / TAU)
    out["at_pause"] = float(ratio[-1])
    out["vs_pre_ramp_best"] = float((mse[on_ramp] / mse[~on_ramp].min()).max())
    out["best"] = float(mse.min())
    over = np.flatnonzero(ratio > 3.0)
    out["over_3x_at"] = float(a[idx[over[0]], 2] / TAU) if over.size else None
    return out


@pytest.fixture(scope="module")
def ramp() -> dict:
    out = drift(DRIFT_RATE)
    print({k: v for k, v in out.items() if k != "view"})
    return out


def test_a_drifting_plant_is_paused_soon_after_it_leaves_the_envelope(ramp):
    view = ramp["view"]
    assert view.counters.identified >= 1 and view.counters.steps > 10
    assert view.counters.envelope_pauses >= 1 and view.identification.out_of_envelope
    # out of the envelope from tau = 3 tau0 (apparent 1.5); caught within 0.5 tau0 more
    # (identification sees the plant about three moves late: its six events' mean)
    assert EDGE < ramp["paused_at"] <= EDGE + 0.5


def test_the_model_check_keeps_the_unchanged_plant_within_3x_of_its_best(ramp):
    """The bar's MSE line before the ramp: the agent's steps the identified model predicts
    worse are held (without the check: 134-1,200x), and re-estimates of the same plant do
    not move the gains (``model_check.MOVED``)."""
    assert ramp["view"].counters.model_holds > 0
    assert ramp["followed_before_ramp"] == 0
    assert ramp["before_ramp"] <= 3.0


def test_the_gains_follow_the_drifting_plant(ramp):
    """On the ramp each confident model that shows the plant moved, and predicts the gains
    in force worse than 1.5x its tuning, puts its tuning in force: the MSE stays within
    74x its best up to the pause (22x at it), where gains held on the first model's tuning
    reached 1,760x (main before session 12)."""
    assert ramp["followed"] >= 10
    assert ramp["on_ramp"] < 150.0 and ramp["at_pause"] < 50.0


def test_the_step_test_passes_3x_its_best_within_identifications_error():
    """Why the 3x line is missed on every ramp: the model tuning best on the plant (the
    true model's SIMC, ``first_tuning.model_gains``) passes 3x its MSE when tau rises by
    5 % (3.6x); the identified models of this loop are off by 2-4 % in tau on the
    unchanged plant (their tunings' MSE scatter by 1.3-4.6x) and lag a drifting plant by
    about three moves (they fit its last six)."""
    kp, ki = model_gains(K, TAU, THETA)
    best, later = agent_mse([kp, kp], [ki, ki], [TAU, 1.05 * TAU])
    assert later > 3.0 * best


if __name__ == "__main__":  # the table in docs/identification.md: RATE... (or "steps")
    for arg in sys.argv[1:]:
        result = drift(None if arg == "steps" else float(arg))
        result.pop("view")
        print(json.dumps({"rate": arg, **result}), flush=True)
