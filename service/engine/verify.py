"""Verify-or-rollback: every change of a loop's gains is judged against its last-good gains.

Per loop the engine keeps the **last-good** gains and their figure (the IAE of a setpoint
response normalised by the move, s: :mod:`service.engine.monitor`). The gains in force
differing from them is a change **pending** verification (whoever made it: an agent
step, a reset, an operator's change the gateway reported, an accepted proposal). Each
complete setpoint response judges the gains in force at its move (the candidate):

* no figure yet for the last-good gains: the response's figure becomes it (the first
  response after registration is the baseline), and the candidate is ``verified``;
* candidate equal to the last-good gains: the figure refreshes theirs (mean of the two);
* figure worse than ``(1 + verify_margin)`` times the last-good one: the change failed;
* otherwise the candidate is ``verified`` and becomes the last-good gains with its figure.

An oscillation (:func:`service.engine.oscillation.detect`) while a change is pending
fails the change at once. Last-good gains the detector flagged while they were in force
(after they became last-good) are **discredited** (:func:`discredited`): the plant they
were verified on has changed, or the loop is driven from outside. A change that then
fails on IAE or overshoot is not rolled back to them: it stays, verdict ``worse``, and
becomes the last-good gains, measured anew (:func:`_keep`); a change that oscillates
is still rolled back. An operator's detune (:func:`adopted`) is never rolled back (nor
proposed away) automatically: it is kept the same way when it fails, and until a verdict
it is the floor of rollbacks (a change from it that fails goes back to it, not past it). A failed
change is acted on by mode: ``auto`` restores the
last-good gains (published, reason ``rollback``; the agent's hidden state restarts and
the agent is held for ``cooldown_periods`` RL periods), ``advisory`` proposes them (an
advisory message, reason ``rollback``: verdict ``rollback_proposed``), ``shadow`` and
``frozen`` only record verdict ``worse`` (nothing may be published for them).

Verdicts of the changes up to a seq are audit rows (reason ``verified``, ``rollback`` or
``verdict``) whose JSON detail names the seqs judged; changes after the loop's judged seq
(:attr:`v_seq`) are ``pending``. All of it is in the loop's runtime snapshot, and the
daemon snapshots a loop whose verification state moved before it publishes.

Advisory and shadow loops keep a **proposal track** of proposals the operator accepts or
rejects: :mod:`service.engine.track`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import orjson

from service.engine import track
from service.engine.audit import audit_row
from service.engine.fences import FENCED, ROLLBACK, cool, fence_rollback, unfence
from service.engine.modes import AUTO, PUBLISHING
from service.engine.monitor import ABSENT, RESPONSE_PERIODS, put, same_gains
from service.engine.oscillation import forget_lobes, noise_sigma, period
from service.engine.reported import held, is_detune, no_floor, outside, within
from service.engine.updates import MODE_VALUES, StepResult, published
from service.wire.protocol import UpdateReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable

F64 = [
    # last-good gains (restored exactly by a rollback) and their seq
    "g_kp", "g_ki", "g_seq",
    # changes up to this seq are judged; the agent is held until this plant time (why)
    "v_seq", "cool_until", "cool_why",
    # the proposal track of advisory and shadow loops (NaN: none), its seq, reason code
    # and the plant time it was made (service.engine.track)
    "adv_kp", "adv_ki", "adv_seq", "adv_why", "adv_t",
    # the fence after a rollback: bounds of the agent's gains (NaN: none) until a plant time
    "x_kp_lo", "x_kp_hi", "x_ki_lo", "x_ki_hi", "x_until",
    # tuning paused until this plant time (the loop oscillates), and the last plant time
    # the oscillation detector flagged the loop, and flagged it at the last-good gains
    # since they became last-good (-inf: never)
    "osc_until", "osc_seen", "g_osc",
    # an operator's detune of the last-good gains, adopted since they were set (NaN:
    # none): no automatic rollback goes past it
    "o_kp", "o_ki",
    # the gains last adopted from the gateway (NaN: none): outside the guard's bounds,
    # and still in force, they hold the loop (reported.held)
    "a_kp", "a_ki",
]  # fmt: skip
"""Per-loop float64 arrays of verification (allocated by the table beside its own)."""
F32 = [
    # the last-good gains' figures (normalised IAE, s, of upward and of downward setpoint
    # moves: a non-linear plant answers the two differently; NaN: none yet)
    "g_iae", "g_iae_dn",
    # margin and overshoot limit (NaN: verification off), cool-down and fence (s) of the guard
    "v_margin", "v_over", "v_cool", "v_fence",
    # gains judged worse and kept (advisory: the proposal not taken; shadow, frozen):
    # not judged again on every response (compared within GAIN_RTOL, which float32 holds)
    "b_kp", "b_ki",
    # 1: the last-good gains have had a setpoint response without an oscillation
    "g_calm",
]  # fmt: skip
"""Per-loop float32 arrays of verification: figures and settings."""
_STATE = [n for n in F64 + F32 if n not in ("v_margin", "v_over", "v_cool", "v_fence")]
"""What the runtime snapshot keeps (the settings come from the config)."""

_MINUS_INF = ("cool_until", "x_until", "osc_until", "osc_seen", "g_osc")
"""Plant times whose "never" is -inf (a snapshot writes it as null)."""

Verdict = str
"""``verified``, ``rolled_back``, ``rollback_proposed``, ``worse`` or ``pending``."""


def init(tb: LoopTable, s: int) -> None:
    """A new loop: its gains are the last-good ones, not yet measured."""
    tb.g_kp[s], tb.g_ki[s] = tb.kp[s], tb.ki[s]
    tb.g_iae[s] = tb.g_iae_dn[s] = math.nan
    tb.g_seq[s] = tb.v_seq[s] = tb.seq[s]
    tb.cool_until[s] = -math.inf
    track.restart(tb, s)
    tb.b_kp[s] = tb.b_ki[s] = math.nan
    tb.osc_until[s] = tb.osc_seen[s] = tb.g_osc[s] = -math.inf
    tb.g_calm[s] = 0.0
    tb.a_kp[s] = tb.a_ki[s] = math.nan
    unfence(tb, s)
    no_floor(tb, s)


def configure(
    tb: LoopTable, s: np.ndarray, on, margin, overshoot, cooldown_periods, fence_periods
) -> None:
    """The guard's verification settings of the loops at slots ``s`` (aligned arrays of
    the settings; after their RL periods are set)."""
    tb.v_margin[s] = np.where(on, margin, math.nan)
    tb.v_over[s] = np.where(on, overshoot, math.nan)
    period = tb.period[s]
    finite = np.isfinite(period)
    seconds = np.where(finite, period, 0.0)
    tb.v_cool[s] = np.where(finite, cooldown_periods * seconds, 0.0)
    tb.v_fence[s] = np.where(finite, fence_periods * seconds, 0.0)


def adopted(tb: LoopTable, s: int, old: tuple[float, float]) -> None:
    """Gains an operator set in the DCS replaced ``old`` in slot ``s`` (adopted from the
    samples): the agent starts from them, unfenced, an advisory loop's proposals too (as
    at a reject). A detune of the last-good gains (:func:`~service.engine.reported.
    is_detune`; of the verified gains, not of a pending change it backs off from) is the
    floor of automatic rollbacks (:func:`fail`) until a verdict sets new last-good gains;
    gains outside the guard's bounds hold the loop while in force
    (:func:`~service.engine.reported.held`)."""
    unfence(tb, s)
    track.restart(tb, s)
    # judged from the loop's seq on: an operator's change takes no seq (a seq unpublished
    # would be news to a gateway's state query, which would then write these gains over
    # a later change of the operator's), it shares that of the last update it replaced
    if not math.isnan(tb.v_margin[s]):
        tb.v_seq[s] = min(tb.v_seq[s], tb.seq[s] - 1)
    # a response open across it judges neither gains (as one a gap cuts short): judged
    # on it, the gains it replaced were verified after it and its own verdict lost
    tb.r_t0[s] = math.nan
    new = _gains(tb, s)
    good = (float(tb.g_kp[s]), float(tb.g_ki[s]))
    tb.o_kp[s], tb.o_ki[s] = new if is_detune(good, new) else (math.nan, math.nan)
    tb.a_kp[s], tb.a_ki[s] = new
    tb._verify_dirty.add(s)


def changed(tb: LoopTable, s):
    """Whether the gains in force differ from the last-good ones (a change is pending);
    ``s`` a slot or an array of them."""
    return ~(same_gains(tb.kp[s], tb.g_kp[s]) & same_gains(tb.ki[s], tb.g_ki[s]))


def judge(tb: LoopTable, done: np.ndarray, osc: np.ndarray, wall: float) -> list[StepResult]:
    """Verdicts of the loops whose response just completed (``done``) or that just
    started oscillating (``osc``); returns the rollbacks to publish."""
    out: list[StepResult] = []
    for s in done.tolist():
        if math.isnan(tb.v_margin[s]) or not math.isfinite(tb.f_iae[s]) or held(tb, s):
            continue
        figure, cand = float(tb.f_iae[s]), (float(tb.r_kp[s]), float(tb.r_ki[s]))
        seq = int(tb.r_seq[s])
        is_good = bool(same_gains(cand[0], tb.g_kp[s]) & same_gains(cand[1], tb.g_ki[s]))
        if tb.r_mixed[s] and (is_good or not changed(tb, s)):
            # the gains changed during it: no figure of the last-good gains, and none of
            # gains since rolled back (nothing is pending: judged, they were judged twice)
            continue
        good = float(reference(tb, s))
        calm = bool(tb.osc_seen[s] < tb.f_t[s] - RESPONSE_PERIODS * tb.period[s])
        if is_good and math.isfinite(good):
            _set_reference(tb, s, 0.5 * (good + figure))
            tb.v_seq[s] = max(tb.v_seq[s], seq)
            tb.g_calm[s] = max(float(tb.g_calm[s]), float(calm))
            continue
        if same_gains(cand[0], tb.b_kp[s]) & same_gains(cand[1], tb.b_ki[s]):
            tb.v_seq[s] = max(tb.v_seq[s], seq)  # judged worse already, kept by the operator
            continue
        over = overshoot(tb, s)
        if not is_good and over > tb.v_over[s]:
            result = fail(tb, s, "overshoot", wall, figure=figure, overshoot=over)
            if result is not None:
                out.append(result)
            continue
        if math.isfinite(good) and figure > (1.0 + tb.v_margin[s]) * good:
            result = fail(tb, s, "iae", wall, figure=figure)
            if result is not None:
                out.append(result)
            continue
        first = int(tb.v_seq[s]) + 1
        _verified(tb, s, cand, seq, figure)
        tb.g_calm[s] = float(calm)
        if is_good:  # nothing was pending: the baseline of unchanged gains
            continue
        ident = tb.ident[s]
        if ident is not None and first <= ident.tuned_seq <= seq:  # a model's tuning held
            ident.tuned_seq, ident.tuned = -1, None  # the agent until its verdict
            tb.cool_until[s] = min(tb.cool_until[s], float(tb.last_t[s]))
        _audit(tb, s, wall, "verified", cand, cand, {
            "verdict": "verified", "seqs": [first, seq], "iae": figure,
            "good_iae": None if math.isnan(good) else good, "baseline": math.isnan(good),
        })  # fmt: skip
    for s in osc.tolist():
        if math.isnan(tb.v_margin[s]) or not changed(tb, s) or held(tb, s):
            continue
        result = fail(tb, s, "oscillation", wall, figure=None)
        if result is not None:
            out.append(result)
    return out


OSC_PAUSE_PERIODS = 2.0
"""Oscillation periods tuning stays paused after the detector last flagged the loop: a
setpoint move restarts the detector, which needs three half-periods to flag the same
oscillation again, and the agent must not step in between."""


def pause_oscillating(tb: LoopTable, slots: np.ndarray, t: np.ndarray, wall: float) -> None:
    """Tuning pauses while a loop oscillates at last-good gains that were calm (had a
    setpoint response without an oscillation), and for :data:`OSC_PAUSE_PERIODS` after
    (status ``oscillating``): the oscillation is not the gains' doing (an oscillating
    load, an upstream loop cycling, a sticking valve, or a plant that changed), and the
    agent would learn from it, and its changes be judged by it, as if it were the loop's
    response. (A change pending when the detector flags is failed at once by
    :func:`judge`; gains that oscillated from the start, an operator's, are the agent's
    to detune: no pause.) A pause that begins is an audit row (reason ``oscillating``)
    and a counter. ``slots`` distinct, ``t`` their samples' plant times."""
    if not tb.verifying:
        return
    flag = tb.o_osc[slots] & np.isfinite(tb.v_margin[slots])
    if not flag.any():
        return
    tb.osc_seen[slots[flag]] = t[flag]
    flag &= ~changed(tb, slots)
    tb.g_osc[slots[flag]] = t[flag]  # at the last-good gains: no rollback to them now
    flag &= tb.g_calm[slots] == 1.0
    if not flag.any():
        return
    s, tf = slots[flag], t[flag]
    began = ~(tf < tb.osc_until[s])
    per = tb.o_per[s].astype(np.float64)
    per = np.where(np.isfinite(per) & (per > 0.0), per, tb.period[s])
    tb.osc_until[s] = tf + OSC_PAUSE_PERIODS * per
    for i in np.flatnonzero(began).tolist():
        k = int(s[i])
        tb.n_osc_pauses[k] += 1
        tb._verify_dirty.add(k)
        _audit(tb, k, wall, "oscillating", _gains(tb, k), _gains(tb, k), {
            "period_s": _num(per[i]), "oscillation_index": _num(tb.o_index[k]),
            "until_t": float(tb.osc_until[k]),
        }, t=float(tf[i]))  # fmt: skip


def paused(tb: LoopTable, slots, t) -> np.ndarray:
    """Where tuning pauses because the loop oscillates (:func:`pause_oscillating`) at
    plant times ``t`` (aligned with ``slots``)."""
    return tb.verifying & np.isfinite(tb.v_margin[slots]) & (t < tb.osc_until[slots])


def _gains(tb: LoopTable, s: int) -> tuple[float, float]:
    return float(tb.kp[s]), float(tb.ki[s])


def overshoot(tb: LoopTable, s: int) -> float:
    """The last complete response's overshoot past the new setpoint, share of the move,
    less 3 noise sigmas (what noise alone could show); NaN without a figure."""
    move = abs(float(tb.f_move[s]))
    if not move > 0.0:  # a move float32 holds as 0: nothing to judge an overshoot by
        return math.nan
    return float(tb.f_over[s]) / 100.0 - 3.0 * float(noise_sigma(tb, np.array([s]))[0]) / move


def reference(tb: LoopTable, s):
    """The last-good figure a response is judged against: of its own direction (``s``
    a slot or slots; the direction of the last complete response, not of one the same
    sample may have opened)."""
    return np.where(tb.f_move[s] < 0, tb.g_iae_dn[s], tb.g_iae[s])


def _set_reference(tb: LoopTable, s: int, value: float) -> None:
    if tb.f_move[s] < 0:
        tb.g_iae_dn[s] = value
    else:
        tb.g_iae[s] = value


def forget_figures(tb: LoopTable, s: int) -> None:
    """Drop slot ``s``'s last-good figures when identification shows the plant moved
    (:func:`service.engine.model_check.plant_moved`): the next response of either
    direction is a baseline again, as after registration. Judged against the figure of
    the plant of before, every step that followed a plant slowing down failed on IAE
    (the slower plant's responses take longer whatever the gains: docs/tuner.md,
    Adaptation through the engine). Overshoot and oscillation verdicts still apply."""
    if math.isnan(tb.g_iae[s]) and math.isnan(tb.g_iae_dn[s]):
        return
    tb.g_iae[s] = tb.g_iae_dn[s] = math.nan
    tb._verify_dirty.add(s)


def _verified(tb, s: int, cand: tuple[float, float], seq: int, figure: float) -> None:
    # the other direction keeps the last-good gains' figure: the next response that way
    # is judged against it, like with like
    tb.g_kp[s], tb.g_ki[s], tb.g_seq[s] = cand[0], cand[1], seq
    tb.g_osc[s] = -math.inf
    no_floor(tb, s)
    _set_reference(tb, s, figure)
    tb.v_seq[s] = max(tb.v_seq[s], seq)
    tb._verify_dirty.add(s)


def fail(
    tb: LoopTable,
    s: int,
    why: str,
    wall: float,
    *,
    figure: float | None,
    actor: str = "",
    overshoot: float | None = None,
) -> StepResult | None:
    """A change failed (or an operator asked for a rollback): act by mode. Returns the
    message to publish (auto: the rollback; advisory: the rollback proposal)."""
    mode = int(tb.mode[s])
    old = (float(tb.kp[s]), float(tb.ki[s]))
    # the last-good gains within the configured bounds (a PATCH may have narrowed them
    # since: restored as they were, a rollback went back above kp_max 14 times)
    good = within(tb, s, (tb.g_kp[s], tb.g_ki[s]))
    judged = [int(tb.v_seq[s]) + 1, int(tb.seq[s])]
    detail = {"why": why, "seqs": judged, "iae": figure, "good_iae": _num(reference(tb, s)),
              "oscillation_index": _num(tb.o_index[s])}  # fmt: skip
    if why == "oscillation":
        detail["period_s"] = period(tb, s)
    if overshoot is not None:
        detail["overshoot"] = overshoot
    if actor:
        detail["actor"] = actor
    tb._verify_dirty.add(s)
    t = float(tb.last_t[s]) if math.isfinite(tb.last_t[s]) else 0.0
    if discredited(tb, s) and why != "oscillation" and not actor:
        return _keep(tb, s, old, wall, detail, KEPT_DISCREDITED)
    floor = (float(tb.o_kp[s]), float(tb.o_ki[s]))
    if mode in PUBLISHING and not actor and not math.isnan(floor[0]):
        if same_gains(old[0], floor[0]) & same_gains(old[1], floor[1]):
            return _keep(tb, s, old, wall, detail, KEPT_DETUNE)
        good = within(tb, s, floor)
        tb.o_kp[s], tb.o_ki[s] = good  # within the bounds in force, as the gains restored
        detail["to"] = "the operator's detune"
    else:
        floor = None
        no_floor(tb, s)
    if mode != AUTO:
        tb.b_kp[s], tb.b_ki[s] = old
    if mode not in PUBLISHING:
        tb.v_seq[s] = tb.seq[s]
        _audit(tb, s, wall, "verdict", old, old, {"verdict": "worse", **detail})
        return None
    if mode != AUTO and not actor and track.pending(tb, s, good, UpdateReason.rollback):
        return None  # that rollback waits for the operator already, under its own seq
    tb.seq[s] += 1
    cool(tb, s, t, ROLLBACK)
    seq = int(tb.seq[s])
    tb._gains_dirty.add(s)
    if mode == AUTO:
        tb.prev_kp[s], tb.prev_ki[s] = old
        tb.kp[s], tb.ki[s] = good
        tb.pending[s], tb.auto_seq[s] = True, seq
        tb.hidden[s] = 0.0  # the agent's memory of the failed gains goes with them,
        tb.unsettle(s)
        forget_lobes(tb, s)  # the detector's of their ringing too
        if why in FENCED:
            fence_rollback(tb, s, old, good, t)
        track.restart(tb, s)
        verdict = "rolled_back"
    else:
        track.propose(tb, s, good[0], good[1], seq, UpdateReason.rollback)
        verdict = "rollback_proposed"
    ident = tb.ident[s]
    if why in REFUTING and ident is not None and judged[0] <= ident.tuned_seq <= judged[1]:
        tb.refuted.append(s)  # the model's tuning rang: the model is wrong
        detail["model"] = "refuted: identification restarts"
    # gains restored are judged no more; an operator's detune, or last-good gains clipped
    # to bounds a PATCH narrowed, are new gains: judged from this seq (a verdict's seqs)
    kept = same_gains(good[0], tb.g_kp[s]) & same_gains(good[1], tb.g_ki[s])
    tb.v_seq[s] = seq if floor is None and kept else seq - 1
    _audit(tb, s, wall, "rollback", old, good, {"verdict": verdict, **detail}, t=t)
    why_text = f"reason=rollback why={why} verdict={verdict}"
    return single(tb, s, t, old, good, UpdateReason.rollback, why_text, mode)


REFUTING = ("oscillation", "overshoot")
"""Verdicts on a model's tuning (first_tuning.py) that refute the model: the loop rang
at it; a worse IAE alone is no proof (noise, a load in the judged window)."""


def discredited(tb: LoopTable, s: int) -> bool:
    """The last-good gains oscillated in force since they became last-good (not the tail
    of a rollback's ringing: :func:`forget_lobes`): the plant they were verified on has
    changed (or the oscillation comes from outside); restoring them is no safety."""
    return bool(tb.g_osc[s] > -math.inf)


KEPT_DISCREDITED = "kept: the last-good gains oscillated in force since they were verified"
KEPT_DETUNE = "kept: an operator's detune is not undone automatically"


def _keep(tb: LoopTable, s: int, gains: tuple[float, float], wall: float, detail: dict, note):
    """A change judged worse that is not rolled back: it stays, as the new last-good
    gains, measured anew (the next response of either direction is their baseline),
    verdict ``worse``, the ``note`` saying why. Two cases:

    * the last-good gains are :func:`discredited` (and the change did not oscillate);
    * in ``auto`` or ``advisory``, the change is an operator's detune (:func:`adopted`),
      whatever the verdict: its IAE is judged against a figure of the plant as it was,
      and an operator detunes because the loop rings. Restored, the last-good gains
      undid such a detune of a plant that had changed, to gains with a gain margin of
      1.0 on it, which then oscillated for hours (session 36's safety review; the
      oscillation detector had not flagged them in force, an agent step was pending
      when the loop began to ring).
      The rollback is an operator's call (``POST /loops/{id}/rollback``, before the
      verdict), and a later change that fails goes back to the detune, not past it."""
    _verified(tb, s, gains, int(tb.seq[s]), math.nan)
    forget_figures(tb, s)  # both directions' (_verified sets the one of the last move)
    tb.g_calm[s] = 0.0
    _audit(tb, s, wall, "verdict", gains, gains, {"verdict": "worse", "kept": note, **detail})
    return None


def reset(tb: LoopTable, s: int) -> None:
    """A loop reset (in ``auto`` its registration's gains back): no hold after a
    rollback, no oscillation pause, no fence, no proposal, no operator's floor. (A loop
    held for gains reported outside the bounds stays held while they are in force: a
    reset of an advisory, shadow or frozen loop leaves them.)"""
    tb.cool_until[s] = tb.osc_until[s] = -math.inf
    unfence(tb, s)
    no_floor(tb, s)
    track.restart(tb, s)
    tb._verify_dirty.add(s)


def single(tb, s, t, old, new, reason: UpdateReason, why: str, mode: int) -> StepResult:
    """A one-loop decision to publish (rollback, accepted proposal, model tuning, reset)."""
    return published(tb, np.array([s]), StepResult(
        [tb.ids[s]], np.array([t]), tb.seq[[s]].copy(), np.array([mode]), np.array([old]),
        np.array([new]), np.array([new]), [tb.gateways[s]], reason, why=[why],
    ))  # fmt: skip


def _audit(tb, s, wall, reason, old, new, detail: dict, t: float | None = None) -> None:
    t = (float(tb.last_t[s]) if math.isfinite(tb.last_t[s]) else None) if t is None else t
    tb._audit.append(
        audit_row(tb.ids[s], wall, t, int(tb.seq[s]), MODE_VALUES[tb.mode[s]], reason, old, new,
                  orjson.dumps(detail).decode())
    )  # fmt: skip


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def dumps(tb: LoopTable, slots: np.ndarray) -> list[dict]:
    """The verification state of the loops at ``slots`` for the runtime snapshot, one
    dict each (NaN and inf stay: the snapshot's orjson writes them as null); each array
    read once for all of them."""
    columns = [getattr(tb, name)[slots].tolist() for name in _STATE]
    return [dict(zip(_STATE, values, strict=True)) for values in zip(*columns, strict=True)]


def load(tb: LoopTable, slots: np.ndarray, dicts: list[dict]) -> None:
    """The verification state of snapshots (:func:`dumps`' dicts) into the loops at
    ``slots``, one assignment per array (a name a snapshot lacks stays as it is)."""
    for name in _STATE:
        default = -math.inf if name in _MINUS_INF else math.nan
        put(getattr(tb, name), slots, [d.get(name, ABSENT) for d in dicts], default)
    # snapshots from before session 37 have no adopted gains: gains in force outside the
    # bounds are taken as adopted (held), as they would have been adopted now
    old = slots[np.array(["a_kp" not in d for d in dicts], bool)]
    old = old[outside(tb, old)]
    tb.a_kp[old], tb.a_ki[old] = tb.kp[old], tb.ki[old]
