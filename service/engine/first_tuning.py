"""The first tuning from an identified model: when identification puts a model in force
(a loop registered without a hint, or a wrong hint rescaled), gains below the model's
textbook tuning are raised to it in one guarded, audited change, instead of the agent
walking them up by ``max_rel_change`` per update; after a rescale, and when the envelope
guard pauses a loop, gains off it either way are set to it (:data:`REPLACE_AFTER`).

The tuning is the improved SIMC rule (Grimholt & Skogestad 2012,
:func:`plant_sim.tunings.simc_improved`: ``Kc = (tau + theta/3) / (K (tau_c + theta))``,
``tau_I = min(tau + theta/3, 4 (tau_c + theta))``) detuned to ``tau_c = 2 tau`` (a closed
loop twice as slow as the plant: the paper's target trajectory, and the reference tuning
``pitune demo`` reports). In the agent's units (gain and tau 0.5, theta/tau 0..1) it lands
within 0-14% of the best fixed PI for the step-test metric the agent was trained on
(``plant_sim.tunings.oracle``): where the agent would take the loop. With the model's tau
30% off either way (theta off the other way, their sum kept: the error closed-loop data
leave) its step-test MSE stays below 0.007 (the paper's SIMC variant, ``tau_c = 2 tau``
with the original rule's gain: up to 0.03). For a newly identified loop each gain is
raised to the model's, never lowered (a loop already tuned faster keeps its gains, and
the agent starts from them), and only when one is more than one guard step
(``1 + max_rel_change``) below (the agent's own next step reaches the rest). After a
rescale or an envelope pause the gains in force are the agent's, tuned for the wrong
plant, and both are set to the model's when either is more than a guard step off it.
The guard's bounds apply.

The change is a decision like any other: published (``auto``: reason ``model``, pending
verification) or proposed (``advisory``), recorded in the audit log (reason ``model``,
the model and the rule in its detail), and judged by verify-or-rollback on the next
setpoint response against the last-good gains (a model-based tuning that makes the loop
worse is rolled back, and one that makes it oscillate at once). The agent is held until
that verdict, at most ``cooldown_periods`` RL periods (the hold after a rollback), then
continues from a hidden state warmed on the model (:func:`flush`,
:mod:`service.engine.warm`: from a zero state it moved the gains 14-50 % a step and the
two-tank demo ended at 7x the hinted run's MSE), and while the model is in force its
gains stay within ``guard.model_band`` of the model's tuning (:func:`band`: on noisy
loops whose setpoint moves every RL period or so, the agent, hinted or not, walks the
integral gain to 0.2-0.5 of it, a step-test MSE 30-100x the model tuning's). A loop
registered without a hint has no measured figure for its old gains (the monitor's target
needs a model): its first response after the change becomes the baseline, and the
model's predicted IAE before and after (:mod:`service.engine.predict`) is in the audit
row. Shadow and frozen loops get none (nothing may be published for them); their agent
starts from the gains in force, and so do all loops while the plant is held
(:mod:`service.engine.plant_hold`).
"""

from __future__ import annotations

import math

import numpy as np

from plant_sim.tunings import simc_improved, to_parallel
from service.engine import box, fences, predict, reported, track, verify, warm
from service.engine.modes import AUTO, FROZEN, PUBLISHING
from service.wire.protocol import UpdateReason

RULE = "simc_improved tau_c=2tau"
"""The rule's name in the audit row."""
WARMED = ("identified", "rescaled", "followed")
"""Decisions that put a model's tuning in force and restart the agent's episode: the
agent's hidden state and error integral then come from a run on the model
(:mod:`service.engine.warm`), not from zero nor (``followed``: the plant moved) from the
plant of before (whose state a followed loop loses at the decision, so a warm result
dropped as out of date leaves a fresh state, as for the other two). Not ``checked``: it
corrects the agent's own first tuning of the same plant, whose memory is still its.
Why ``followed``: after a tau ramp the agent, its state still the faster
plant's, walked the followed tuning's kp down 25 % (evaluation's adaptation through the
engine, paper's tau ramp: step-test MSE 0.0018, 0.00093 warmed; the spread's 8 tau ramps
0.00099 / 0.0038 geometric mean / worst, 0.00050 / 0.0013 warmed; its K steps the same,
docs/tuner.md)."""
TAU_C = 2.0
"""The closed-loop time constant, in plant time constants (detuned: SIMC's own choice is
``tau_c = theta``)."""
REPLACE_AFTER = ("rescaled", "out_of_envelope", "followed", "checked")
"""Decisions after which the model's tuning replaces the gains both ways, not only raises
them: the gains in force were the agent's, tuned for the plant a wrong scaling described
(or one outside its box, or an earlier model of a plant that has since moved:
``followed``, :func:`service.engine.model_check.follow`; or the agent's, unchecked
until a hinted loop's first confident model predicted them much worse than its own:
``checked``, :func:`service.engine.model_check.hint_checked`), so a faster tuning among them
is no choice to keep (an integral time of 0.4-0.6 of the true tau after a tau hint 2-3x
off: docs/identification.md)."""
FOLLOW = 1.15
"""Factor off the latest confident model's tuning beyond which a loop paused out of the
envelope (no agent step moves it) is set to it again: the first confident model of a
dead-time dominant plant is often off by 20-40 % in tau and its tuning, whose step-test
MSE at theta/tau 2 is 4x that of the true model's (0.037 against 0.0045 on the worst loop
of ``pitune evaluate --robust``), is refined as later models come."""


def model_gains(k: float, tau: float, theta: float) -> tuple[float, float]:
    """The model's tuning (kp, ki per second) in engineering units."""
    kp, ki = to_parallel(*simc_improved(k, tau, theta, TAU_C * tau))
    return float(kp), float(ki)


def band(tb, s: int, m, factor: float) -> None:
    """Narrow slot ``s``'s gain bounds (set from its config) to ``factor`` either way of
    model ``m``'s tuning (``guard.model_band``): the agent refines the model's tuning
    within it instead of walking the gains off it on a noisy loop. Bounds that leave no
    overlap with the band are kept as they are (the user's word)."""
    if m.integrating or not m.k > 0:
        return
    kp, ki = model_gains(m.k, m.tau, m.theta)
    lo = (max(tb.kp_min[s], kp / factor), max(tb.ki_min[s], ki / factor))
    hi = (min(tb.kp_max[s], kp * factor), min(tb.ki_max[s], ki * factor))
    if lo[0] < hi[0] and lo[1] < hi[1]:
        (tb.kp_min[s], tb.ki_min[s]), (tb.kp_max[s], tb.ki_max[s]) = lo, hi


def apply(tb, s: int, m, wall: float, why: str) -> None:
    """Raise the gains of slot ``s`` to model ``m``'s tuning if they are well below it, or
    after a decision in :data:`REPLACE_AFTER` set them to it if they are well off it
    either way (after the model's scaling and bounds are configured); queues the decision
    to publish in ``tb.decided``. ``why``: ``identified``, ``rescaled``,
    ``out_of_envelope``, ``followed`` or ``checked``; those in :data:`WARMED` also queue
    the loop's warm start (:func:`flush`), shadow loops included (their agent steps
    too)."""
    mode = int(tb.mode[s])
    # nothing of the tuner's own while the plant is held (plant_hold.py), as when frozen
    if mode == FROZEN or tb.hold.held or m.integrating or not m.k > 0:
        return
    if why in WARMED:  # from the gains this decision leaves in force
        tb.warming.append((s, tb.ids[s], m))
        if why == "followed":  # the plant of before's memory goes, warm result or not
            tb.hidden[s] = tb.int_e[s] = 0.0
    if (
        mode not in PUBLISHING
        or not tb.configs[tb.ids[s]].guard.model_tuning
        or reported.held(tb, s)
    ):
        return
    old = (float(tb.kp[s]), float(tb.ki[s]))
    target = model_gains(m.k, m.tau, m.theta)
    lo, hi = (tb.kp_min[s], tb.ki_min[s]), (tb.kp_max[s], tb.ki_max[s])
    raised = target if why in REPLACE_AFTER else np.maximum(old, target)
    new = tuple(np.clip(raised, lo, hi).tolist())
    # a followed model's trigger was the predicted step test (model_check.follow): any
    # change of the gains then counts
    step = {"out_of_envelope": FOLLOW, "followed": 1.0}.get(why, 1.0 + float(tb.max_rel[s]))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.asarray(new) / np.asarray(old)
    if not ((ratio > step) | (ratio < 1.0 / step)).any():
        return
    tb.unsettle(s)  # the plant moved, or a new model: the agent's steps whole again
    t = float(tb.last_t[s]) if math.isfinite(tb.last_t[s]) else 0.0
    tb.seq[s] += 1
    seq = int(tb.seq[s])
    tb._gains_dirty.add(s)
    tb._verify_dirty.add(s)
    # the agent is held until the change is verified (at most the cool-down after a
    # rollback)
    fences.cool(tb, s, t, fences.MODEL)
    fences.unfence(tb, s)  # a fence of gains tuned for the plant as it was before
    # a proposal's tuning is judged only once accepted (proposals.accept): until then its
    # seq is no change the loop runs with, and a verdict on the gains in force is not its
    tb.ident[s].tuned_seq, tb.ident[s].tuned = (seq if mode == AUTO else -1), m
    if mode == AUTO:
        tb.prev_kp[s], tb.prev_ki[s] = old
        tb.kp[s], tb.ki[s] = new
        tb.pending[s], tb.auto_seq[s] = True, seq
        track.restart(tb, s)
    else:  # a proposal: the track goes on from it
        track.propose(tb, s, new[0], new[1], seq, UpdateReason.model)
    (predicted,) = predict.predictions(tb, [s], np.array([old]), np.array([new]), [m])
    detail = {
        "rule": RULE, "after": why, "k": m.k, "tau": m.tau, "theta": m.theta,
        "model_kp": target[0], "model_ki": target[1], "predicted": predicted,
    }  # fmt: skip
    verify._audit(tb, s, wall, "model", old, new, detail, t=t)
    verdict = "pending" if mode == AUTO else "proposal"
    with np.errstate(divide="ignore", invalid="ignore"):
        pct = (np.divide(new, old) - 1.0) * 100.0
    guard = "bounds" if not np.allclose(new, raised, rtol=1e-12, atol=0.0) else "none"
    text = (
        f"reason=model basis=model rule=simc dkp={pct[0]:+.1f}% dki={pct[1]:+.1f}% "
        f"guard={guard} verdict={verdict}"
    )
    tb.decided.append(verify.single(tb, s, t, old, new, UpdateReason.model, text, mode))


WARM_PER_PASS = 64
"""Loops warmed in one batch: a warm run costs 7-10 ms a loop on this box at this size
(docs/identification.md), so a pass that puts thousands of models in force at once
(a plant-wide move after a restart) stalls the other loops' samples at most ~0.6 s."""
WARM_SLICE = 2
"""RL steps of the warm run one pass of a budgeted engine takes (of :data:`warm.STEPS
<service.engine.warm.STEPS>`): 15-40 ms of the worker's time (a whole run, 0.17-0.4 s
however few loops it holds, took 58 % of the worker at 2,000 loops identified at once:
``pitune bench --no-hint``)."""


def flush(tb) -> None:
    """Warm the agent of the loops waiting in ``tb.warming`` in one batched run on their
    models from the gains in force (:class:`service.engine.warm.WarmRun`, the model as the
    loop's new scaling shows it), and give each the run's hidden state and error
    integral (the observation's, so divided by the loop's setpoint-move gain). A run
    that goes non-finite leaves its loop's fresh state. At most :data:`WARM_PER_PASS`
    loops a batch: the rest wait for the next (they are held until their model tuning's
    verdict, several RL periods, so none is stepped cold meanwhile). An engine without an
    identification budget runs a batch whole in the pass (an evaluation's numbers do not
    depend on how passes fall); with one (the tuner), :data:`WARM_SLICE` RL steps a
    pass, charged to the budget, and the loops joining meanwhile wait for the next."""
    if tb.warm_run is None:
        items = [
            (s, i, m) for s, i, m in tb.warming[:WARM_PER_PASS]
            if s < len(tb.ids) and tb.ids[s] == i
        ]  # fmt: skip
        del tb.warming[:WARM_PER_PASS]
        if not items:
            return
        slots = np.array([s for s, _, _ in items])
        apps = [box.apparent(tb.scaling_of(s), m) for s, _, m in items]
        K, tau, ratio = (np.array([a[k] for a in apps]) for k in ("gain", "tau", "theta_ratio"))
        run = warm.WarmRun(
            tb, K, tau, tau * ratio, tb.kp[slots] / tb.kp_unit[slots],
            tb.ki[slots] / tb.ki_unit[slots], tb.forgetting[slots],
        )  # fmt: skip
        # what the result may land on: the same loop, model and seq (a reset, a rescale,
        # a restart of identification or a step meanwhile leave the loop's own state)
        keys = [(i, m, int(tb.seq[s])) for s, i, m in items]
        tb.warm_run = (slots, keys, run)
    slots, keys, run = tb.warm_run
    steps = warm.STEPS if tb.fits.share is None else WARM_SLICE
    try:
        if not tb.fits.timed(run.advance, steps):
            return
    except Exception:
        tb.warm_run = None  # a failed run is not resumed
        raise
    tb.warm_run = None
    state, int_e = run.result()
    fine = np.isfinite(state).all(axis=(1, 2)) & np.isfinite(int_e)
    fine &= np.array([_same(tb, int(s), key) for s, key in zip(slots, keys, strict=True)])
    tb.hidden[slots[fine]] = state[fine]
    tb.int_e[slots[fine]] = int_e[fine] / tb.obs_gain[slots[fine]]


def _same(tb, s: int, key: tuple) -> bool:
    loop_id, m, seq = key
    return (
        s < len(tb.ids) and tb.ids[s] == loop_id and tb.ident[s] is not None
        and tb.ident[s].fallback is m and int(tb.seq[s]) == seq
    )  # fmt: skip
