"""Identification's data it must not trust, and a model its own tuning refutes.

A hint-free loop (K 2, tau 40 s, theta 10 s, a sample every 4 s, noise 1, setpoint moves
of +-20 every 5 tau) under a DCS PI (plant_sim), driven through :class:`TuningEngine`:

* an ``op`` sent in other units than the gains (10x the PI law's output) identifies
  nothing (it gave K 0.2 for 2, confident, and a first tuning 10x too high);
* a model whose first tuning makes the loop ring is rolled back to the gains the loop
  had, not to the edge of the model's band, and identification starts again;
* one sample sent a moment after another does not make that moment the sample period.
"""

from __future__ import annotations

import pytest

from plant_sim import FOPTDBatch, PIBatch
from plant_sim.tunings import simc_paper, to_parallel
from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine, watch

pytestmark = pytest.mark.timeout(120)
K, TAU, THETA, H = 2.0, 40.0, 10.0, 4.0
PER_MOVE = int(5 * TAU / H)
REGISTERED = tuple(0.5 * g for g in to_parallel(*simc_paper(K, TAU, THETA)))
"""Half the paper's SIMC tuning (kp, ki per second): a sluggish loop."""


def _run(moves: int, *, op_scale=None, k_after_model=None, t_of=None, manual=0):
    """The loop through the engine for ``moves`` setpoint moves; ``op_scale``: op sent as
    that factor x the PI's output (None: no op); ``k_after_model``: the plant's gain from
    the first model tuning on; ``t_of(j, t)``: the sample times sent; ``manual``: then as
    many output steps of 5 in manual (an operator's bump tests), as long apart. Returns
    the engine, the (t, reason, kp, ki) of the updates and the loop's view after the last
    sample."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(LoopConfig(id="L", kp=REGISTERED[0], ki=REGISTERED[1], sample_period_s=H))
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=1.0, seed=0, max_theta=THETA / H)
    plant.reset(50.0)
    pi = PIBatch(REGISTERED[0], REGISTERED[1] * H, dt=1.0)
    pi.initialise(50.0 / K)
    sp, updates = 50.0, []
    auto_end = (moves + 1) * PER_MOVE
    for j in range(auto_end + manual * PER_MOVE):
        y = float(plant.measure()[0])
        if j < auto_end:
            if j and j % PER_MOVE == 0:
                sp = 50.0 + 20.0 * (1 if (j // PER_MOVE) % 2 else -1)
            u = pi.step(sp - y)
        elif (j - auto_end) % PER_MOVE == 0:  # the output held, stepped by hand
            u = u + 5.0
        t = j * H if t_of is None else t_of(j, j * H)
        sample = {"loop_id": "L", "t": t, "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0] / H), "auto": j < auto_end}  # fmt: skip
        if op_scale is not None:
            sample["op"] = float(op_scale * u[0])
        for up in engine.ingest([sample], wall=float(j)):
            pi.set_gains(up.kp, up.ki * H)
            updates.append((t, str(up.reason), up.kp, up.ki))
            if str(up.reason) == "model" and k_after_model is not None:
                plant.set_params(K=k_after_model)
        plant.step(u)
    return engine, updates, engine.view("L", wall=float(j))


@pytest.mark.parametrize("scale", [10.0, 0.1, -10.0])
def test_an_op_in_other_units_than_the_gains_identifies_nothing(scale):
    _, updates, view = _run(6, op_scale=scale)
    assert updates == [] and view.status == "identifying"
    assert view.identification.in_force is None
    assert "the PI law's output" in view.identification.why
    assert ("inverted" in view.identification.why) == (scale < 0)


def test_an_op_refused_in_auto_stays_refused_through_bump_tests_in_manual():
    """The sums judge the auto data a segment's manual output steps are fitted with: the
    first manual sample cleared them, and the 10x model went in force (K 0.2)."""
    _, updates, view = _run(3, op_scale=10.0, manual=3)
    assert updates == [] and view.identification.in_force is None
    assert "10x the PI law's output" in view.identification.why


def test_an_op_of_the_other_sign_is_the_other_action_as_identification_says():
    """An op that moves against the law one for one is the loop registered with the
    other action: identification's message, which says what to do."""
    _, updates, view = _run(6, op_scale=-1.0)
    assert updates == [] and "action" in view.identification.why


def test_an_op_in_the_gains_units_is_identified():
    _, updates, view = _run(6, op_scale=1.0)
    model = view.identification.in_force
    assert model is not None and abs(model.k / K - 1) < 0.1 and abs(model.tau / TAU - 1) < 0.2
    assert updates and updates[0][1] == "model"


def test_a_model_whose_tuning_rings_is_refuted_and_the_rollback_leaves_its_band():
    """The plant's gain grows 20x as the model's tuning goes out: the loop rings, is rolled
    back to the gains it had before (stable on the new plant; the band's edge, 1.5x
    below the model's tuning, is not) and identification starts again."""
    engine, updates, view = _run(6, k_after_model=20 * K)
    reasons = [u[1] for u in updates]
    assert reasons[:2] == ["model", "rollback"], updates
    rolled = updates[1]
    assert rolled[2:] == pytest.approx(REGISTERED)  # not model tuning / 1.5
    assert updates[0][2] / rolled[2] > 1.5 * 1.05
    rows = [r for r in engine.drain_changes()[1] if r[5] in ("rollback", "identify")]
    assert "refuted" in str(rows[0][10]) and rows[1][5] == "identify"
    assert view.identification.in_force is None or view.identification.in_force.k > 4 * K
    assert watch.REFUTED in str(rows[1][10])


def test_samples_faster_than_registered_are_fitted_at_their_own_period():
    """A gateway sampling every second, a loop registered at 4 s: the fit's period is the
    data's (half the registered one as a floor gave theta 23.7 s and tau 52.9 s, once the
    recorder's rows of 40 samples per tau were merged)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(LoopConfig(id="L", kp=REGISTERED[0], ki=REGISTERED[1], sample_period_s=4.0))
    plant = FOPTDBatch(K, TAU, THETA, dt=1.0, noise_std=1.0, seed=0, max_theta=THETA)
    plant.reset(50.0)
    pi = PIBatch(REGISTERED[0], REGISTERED[1], dt=1.0)
    pi.initialise(50.0 / K)
    sp, per = 50.0, 200
    for j in range(6 * per):
        if j and j % per == 0:
            sp = 50.0 + 20.0 * (1 if (j // per) % 2 else -1)
        y = float(plant.measure()[0])
        u = pi.step(sp - y)
        sample = {"loop_id": "L", "t": float(j), "sp": sp, "pv": y, "op": float(u[0]),
                  "kp": float(pi.kp[0]), "ki": float(pi.ki[0])}  # fmt: skip
        for up in engine.ingest([sample], wall=float(j)):
            pi.set_gains(up.kp, up.ki)
        plant.step(u)
    model = engine.view("L", wall=float(j)).identification.in_force
    assert model is not None and abs(model.tau / TAU - 1) < 0.15
    assert abs(model.theta - THETA) < 0.3 * THETA


def test_one_sample_a_moment_after_another_does_not_set_the_sample_period():
    """Every tenth sample is sent 0.01 s after the one before: identified as without it
    (the fit's period stayed 4 s; it was 0.01 s, every row 400 samples, the noise read
    20x too high and the moves 'too small for the noise')."""

    def t_of(j, t):
        return t - H + 0.01 if j % 10 == 9 else t

    _, _, view = _run(4, op_scale=None, t_of=t_of)
    model = view.identification.in_force
    assert model is not None and abs(model.k / K - 1) < 0.1 and abs(model.tau / TAU - 1) < 0.3
    assert model.noise < 2.0
