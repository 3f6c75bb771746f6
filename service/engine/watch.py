"""Identification inside the engine: each loop's closed-loop data recorded into segments,
assessed at each setpoint move, and the model put to use.

The sample rule (:func:`record`, called by :func:`service.engine.rules.ingest` for every
accepted sample; stated one sample at a time in ``tests/engine_reference.py``):

* Only loops with ``guard.identify`` and samples that carry sp and pv (pv = sp - e).
* The controller output is the sample's ``op``; where absent it is reconstructed from
  the PI law and the gains the tuner holds in force (:func:`~service.engine.identify.
  reconstruct_op`: parallel PI ``u = kp e + I``, ``I' = ki e`` at the sample period,
  bumpless gain changes and from the last ``op`` sent, no feedforward).
* A *segment* opens at a setpoint move (any change of sp) in auto, or at an operator's
  step of the output (:data:`MANUAL_STEP`) in manual with ``op`` sent (a bump test:
  open-loop data; the recorded setpoint stays the one before manual, and the sample
  back in auto is no move: a DCS may track the PV with it), and records every sample
  until a sample in manual without ``op``, saturated, after a stale gap, on a new
  plant clock, after a sample not recorded (no sp) that resumed from such a state, or
  with ``op`` after samples without it breaks it (the data up to there are assessed
  first). After each move the first
  :data:`HEAD_ROWS` rows hold a sample each, later rows the mean of ``stride`` samples;
  a full buffer merges pairs of rows (never a move's first rows) and doubles the
  stride, so the response to each move keeps its shape however long the segment runs.
  A later move closes the running event and opens the next, unless the running event
  holds fewer than :data:`MIN_EVENT_SAMPLES`. The later changes of a ramping setpoint
  (:func:`service.units.ramp_rule`) are samples of the event its first change opened
  (a ramp of one change a sample made an event of every eight samples, none starting at
  rest, and fits confident and wrong); :func:`~service.engine.identify.assess` judges
  whether the ramp was fast enough to tell tau from the dead time.
* At each close the segment is assessed (:func:`~service.engine.identify.assess`) and
  the model used (:mod:`service.engine.model_use`). A confident model without a
  scaling in force becomes the loop's scaling (audit 'identified'); with one in force
  it is compared: a disagreement beyond ``guard.hint_tolerance`` flags the loop (audit
  'mismatch') and, with ``guard.auto_rescale``, rescales it (audit 'rescaled');
  outside the training box by :data:`service.engine.box.ENVELOPE_MARGIN` (or
  integrating) pauses it (audit 'out_of_envelope'; it resumes within
  :data:`~service.engine.box.RESUME_MARGIN`). Both set the gains to the model's
  tuning (:mod:`service.engine.first_tuning`), but for an integrating process, which
  keeps its gains (no tuning of it is trusted: docs/identification.md, Integrating
  processes). A confident model like one whose tuning rang on the loop is not used
  (:mod:`service.engine.refuted`).

The recorder buffers are shared by all loops of a table (a pool of rows, one per open
segment), so memory goes only to loops that are recording.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from service.engine import identify, model_check, model_use, op_law, refuted, verify
from service.engine.foptd_fit import sample_period
from service.engine.id_state import IdState, Refuted
from service.engine.recorder import CAP

MIN_EVENT_SAMPLES = 8
"""Recorded samples an event needs before a new setpoint move closes it."""
MAX_EVENTS = 6
"""Events a segment keeps (older ones are dropped: the plant may drift)."""
CHECK_EVERY = 3
"""With a model in force the latest assessment confirmed, a segment is assessed at every
third event close only (fits cost most); a flagged or paused loop at every one, but one
paused as integrating (:func:`closely`)."""
DRIFT = 1.25
"""Factor (K or tau) by which the latest confident model may differ from the one in force
before the loop is assessed at every chance again (:func:`closely`)."""
HEAD_ROWS = 32
"""Rows of one sample each after a setpoint move, never merged: a segment that halved
all its rows recorded a fast loop's responses in rows of 16-32 samples, and the fits
traded tau for dead time, confident and wrong (tau 6.7 s for 15 s); rows widening with
the time since the move cost dead-time dominant loops (docs/identification.md)."""
MANUAL_STEP = 0.02
"""An output in manual moved by more than this share of its magnitude is an operator's
step (an event; a bump test moves it by 5-10 %); less is noise: a gateway whose ``op`` is
the valve's position feedback (noise up to about 0.3 % of it rms) would otherwise open
an event at every sample or so."""
CHECK_FIRST = 16
"""Samples after a move at which a loop without a confident model is first assessed
within the event (then at 24, 32, 48, 64, 96...: :func:`check_due`)."""


# -- the sample rule ---------------------------------------------------------------------
def record(tb, slots: np.ndarray, cols: dict, last_t: np.ndarray, gap, fresh, wall):
    """Record accepted samples of distinct loops (before ``last_e`` moves on); ``gap``:
    after a stale gap or none before, ``fresh``: that, or back from manual or saturated."""
    t, e, sp = cols["t"], cols["e"], cols["sp"]
    op = cols.get("op")
    tb.fits.refill(wall)  # once per message (service.engine.fit_budget: not steady.now)
    watch = tb.watch[slots] & ~np.isnan(sp)
    if not watch.all():  # a sample not recorded: the next goes on from no recorded one
        rest = slots[~watch]
        tb.prev_ok[rest] = False
        tb.prev_meas[rest] = False if op is None else ~np.isnan(op[~watch])
    if not watch.any():
        return
    idx = np.flatnonzero(watch)
    s, t, e, sp, gap, fresh = slots[idx], t[idx], e[idx], sp[idx], gap[idx], fresh[idx]
    op = np.full(idx.size, np.nan) if op is None else op[idx]
    pv = sp - e
    auto, saturated = cols["auto"][idx], cols["saturated"][idx]
    measured = ~np.isnan(op)
    # the data go on from the last sample, but after a gap, a stretch not recorded, or
    # an output that was reconstructed and is now sent (its constant is unknown)
    anew = (fresh & (gap | ~tb.prev_ok[s])) | (measured & ~tb.prev_meas[s])
    held = tb.id_sp[s]
    # in manual with op sent the operator's output steps are the events and the setpoint
    # (which a DCS may track to the PV) the one before manual; a ramp's later changes
    # are samples of the event its first change opened
    by_hand, back = ~auto & measured, fresh & ~anew  # back: in auto from manual with op
    moved = (sp != held) & ~np.isnan(held) & ~cols["ramping"][idx] & ~by_hand & ~back
    step = _step(op, tb.prev_op[s], tb.oh_hi[s] - tb.oh_lo[s])
    moved |= by_hand & ~anew & (np.abs(op - tb.prev_op[s]) > step)
    sp = np.where(by_hand & ~np.isnan(held), held, sp)
    tb.id_sp[s] = sp
    # the controller output, reconstructed where the sample has none, with the gains the
    # sample reports in force (the DCS's; the tuner's may not have reached it yet), and
    # bumpless from the last one sent (as a DCS block from manual)
    kp = np.where(np.isnan(cols["kp"][idx]), tb.kp[s], cols["kp"][idx])
    ki = np.where(np.isnan(cols["ki"][idx]), tb.ki[s], cols["ki"][idx])
    dt = np.where(anew, 0.0, t - last_t[idx])
    e_prev = tb.last_e[s]
    integral = np.where(anew, 0.0, tb.op_int[s] - (kp - tb.op_kp[s]) * e_prev) + ki * e * dt
    integral = np.where(measured, op - kp * e, integral)
    tb.op_int[s], tb.op_kp[s] = integral, kp
    op = np.where(measured, op, kp * e + integral)
    # gains reported outside the bounds may not be the DCS's: no output from them
    foreign = cols["held"][idx] & ~measured
    broken = anew | (~auto & ~measured) | saturated | foreign
    # whether the op sent is the law's output in the gains' units (op_law.py)
    op_law.observe(
        tb, s, anew, ~broken & auto & measured & (sp == tb.prev_sp[s]) & tb.prev_meas[s],
        kp, ki, e, e_prev, dt, op, tb.prev_op[s],
    )  # fmt: skip
    recording = tb.rec[s] >= 0
    # rare paths, loop by loop: breaks, moves (open or close an event)
    special = np.flatnonzero((recording & broken) | (moved & ~broken))
    done = np.zeros(idx.size, bool)
    for i in np.flatnonzero(moved & broken & ~recording).tolist():  # say why nothing opens
        why = broken_why(auto[i], saturated[i], measured[i], foreign[i])
        what = "output step" if by_hand[i] else "setpoint move"
        tb.ident[int(s[i])].why = f"{what} not usable: {why}"
    for i in special.tolist():
        done[i] = True
        si = int(s[i])
        row = (float(t[i]), float(sp[i]), float(pv[i]), float(op[i]))
        if recording[i] and broken[i]:
            why = broken_why(auto[i], saturated[i], measured[i], foreign[i])
            _close(tb, si, float(t[i]), wall, final=True, why=f"segment ended: {why}")
        elif recording[i]:
            st: IdState = tb.ident[si]
            if tb.rec_n[si] - st.starts[-1] >= MIN_EVENT_SAMPLES:
                _close(tb, si, float(t[i]), wall)
                st.starts.append(int(tb.rec_n[si]))
            _append(tb, si, row, move=True)
        else:
            _open(tb, si, row)
    # the usual path, vectorised: append to open segments at their stride
    plain = np.flatnonzero(~done & recording & ~broken)
    if plain.size:
        ps = s[plain]
        k, m, n = tb.rec_k[ps], tb.rec_m[ps], tb.rec_n[ps]
        tb.rec_k[ps] = k + 1
        # a new row once the last holds a sample (a move's first rows) or a stride's
        take = m >= np.where(n - 1 - tb.rec_ev[ps] < HEAD_ROWS, 1, tb.rec_stride[ps])
        tb.rec_m[ps] = np.where(take, 1, m + 1)
        rows, n = tb.rec[ps[take]], n[take]
        sel = plain[take]
        data = tb.recorder.data
        for c, col in enumerate((t, sp, pv, op)):
            data[rows, c, n] = col[sel]
        tb.rec_n[ps[take]] = n + 1
        # a sample not kept is averaged into the last kept row (see _compress)
        skip = ~take
        if skip.any():
            rows, last = tb.rec[ps[skip]], tb.rec_n[ps[skip]] - 1
            held = m[skip].astype(np.float64)
            for c, col in ((2, pv), (3, op)):
                data[rows, c, last] += (col[plain[skip]] - data[rows, c, last]) / (held + 1.0)
        for si in ps[take][n + 1 >= CAP].tolist():
            _compress(tb, si)
        # a loop not yet confidently identified is assessed during an event too (the
        # response so far: a model can be confident at the move it comes from)
        due = check_due(k)
        for si, ti in zip(ps[due].tolist(), t[plain[due]].tolist(), strict=True):
            if closely(tb, si):
                _close(tb, si, ti, wall)
    tb.prev_t[s], tb.prev_sp[s], tb.prev_pv[s], tb.prev_op[s] = t, sp, pv, op
    tb.prev_ok[s], tb.prev_meas[s] = ~broken, measured


def _step(op, before, span):
    """The least change of the output that is an operator's step in manual:
    :data:`MANUAL_STEP` of its magnitude, or of the range of outputs seen in auto
    (:mod:`service.engine.output_limit`; NaN: none) where that is larger (an output near
    or across zero)."""
    return MANUAL_STEP * np.fmax(np.maximum(np.abs(op), np.abs(before)), span)


def broken_why(auto: bool, saturated: bool, measured: bool, foreign: bool) -> str:
    """Why a sample breaks a segment (or makes a move unusable)."""
    if saturated:
        return "output saturated"
    if foreign:
        return "gains reported outside the guard's bounds, without op in the samples"
    if not auto and not measured:
        return "manual, without op in the samples"
    return "data gap (or samples not recorded before it, or op newly sent)"


def check_due(k):
    """Whether an assessment is due ``k`` samples after a move (int or int array): at
    :data:`CHECK_FIRST` and then every 1.5x or 1.33x further (16, 24, 32, 48, 64, 96...:
    two fits per doubling of the event, so that an event's response is used up to at
    least 2/3 of it before the next move; at powers of two only, 1-3 of the bar's 60
    loops whose first four moves' data were confident were put in force only at the
    fifth move: docs/identification.md)."""
    third = k // 3
    return (k >= CHECK_FIRST) & (
        ((k & (k - 1)) == 0) | ((k % 3 == 0) & ((third & (third - 1)) == 0))
    )


def _open(tb, s: int, row: tuple) -> None:
    r = tb.recorder.take()
    tb.rec[s], tb.rec_n[s], tb.rec_stride[s] = r, 0, 1
    st: IdState = tb.ident[s]
    # the sample before the move (not one from before a new plant clock or a reset)
    if tb.prev_ok[s] and tb.prev_t[s] < row[0]:
        _append(tb, s, (tb.prev_t[s], tb.prev_sp[s], tb.prev_pv[s], tb.prev_op[s]))
    st.starts = [int(tb.rec_n[s])]
    _append(tb, s, row, move=True)


def _append(tb, s: int, row: tuple, move: bool = False) -> None:
    """A row of one sample; ``move``: the sample of a setpoint move (rows of one sample
    follow it, :data:`HEAD_ROWS`)."""
    n = int(tb.rec_n[s])
    tb.recorder.data[tb.rec[s], :, n] = row
    tb.rec_n[s], tb.rec_m[s] = n + 1, 1
    if move:
        tb.rec_k[s], tb.rec_ev[s] = 1, n
    if n + 1 >= CAP:
        _compress(tb, s)


def _compress(tb, s: int) -> None:
    """A full buffer drops its oldest event (keeping one sample before the next) if it
    holds :data:`MAX_EVENTS`, else merges pairs of rows outside each move's first
    :data:`HEAD_ROWS` rows and the row before it. At most MAX_EVENTS - 1 events and the
    running move's rows are kept whole (at most 6 x 33 rows of the 512): a merge frees
    at least a quarter of the buffer."""
    st: IdState = tb.ident[s]
    data = tb.recorder.data[tb.rec[s]]
    n = int(tb.rec_n[s])
    if len(st.starts) >= MAX_EVENTS:
        return _drop_oldest(tb, s, n)
    i = np.arange(n)
    head = np.zeros(n, bool)
    for a in {*st.starts, int(tb.rec_ev[s])}:
        head[max(a - 1, 0) : a + HEAD_ROWS] = True
    # each run of other rows keeps every other row, from its first
    keep = head | ((i - np.maximum.accumulate(np.where(head, i, -1))) % 2 == 1)
    kept = np.flatnonzero(keep)
    # each kept row's measurement and output: their time-weighted means over the rows it
    # now stands for (the output is the input the plant integrates over the row's
    # interval; the mean measurement keeps the information of the samples dropped:
    # keeping one sample in two instead scattered tau by 1.5-1.8x more, and the held
    # output misrepresented the input). The mean measurement lags the row's time by
    # half its interval, which the dead time absorbs.
    t = data[0, :n]
    h = sample_period(t, _registered(tb, s))
    w = np.diff(t, append=t[-1] + tb.rec_m[s] * h)
    span = np.concatenate([[0.0], np.cumsum(w)])
    ends = np.append(kept[1:], n)
    acc = np.zeros((2, n + 1))
    acc[:, 1:] = np.cumsum(data[2:4, :n] * w, axis=1)
    means = (acc[:, ends] - acc[:, kept]) / (span[ends] - span[kept])
    data[:, : kept.size] = data[:, kept]
    data[2:4, : kept.size] = means
    tb.rec_n[s] = kept.size
    tb.rec_m[s] += round((t[n - 1] - t[kept[-1]]) / h)  # the last row: the samples it holds
    st.starts = [int(np.searchsorted(kept, a)) for a in st.starts]
    tb.rec_ev[s] = int(np.searchsorted(kept, tb.rec_ev[s]))
    tb.rec_stride[s] *= 2


def _close(tb, s: int, t: float, wall: float, *, final: bool = False, why: str = "") -> None:
    """Assess the segment so far (its last event complete), or owe the assessment when
    the identification budget is spent (:mod:`service.engine.fit_budget`); ``final``:
    and release it."""
    st: IdState = tb.ident[s]
    n = int(tb.rec_n[s])
    if st.in_force is not None and not final and not closely(tb, s):
        st.skipped += 1  # a model in force the last assessment confirmed: check less often
        if st.skipped < CHECK_EVERY:
            return _trim(tb, s, n)
    st.skipped = 0
    if not tb.fits.allows():  # a segment that ends is released unassessed (a plant trip
        # ends thousands at once: no stall of the samples behind their fits)
        if final:
            st.why = f"{why} (its data not assessed: identification budget spent)"
        else:
            tb.fits.owe(s, urgent=not tb.scaled[s] or closely(tb, s))
    elif tb.fits.timed(_assess, tb, s, t, wall):
        tb.fits.forget(s)  # assessed now: owed nothing more
    elif final:
        st.why = why
    if final:
        tb.fits.forget(s)
        tb.recorder.give(int(tb.rec[s]))
        tb.rec[s] = -1
        st.starts = []
    _trim(tb, s, n)


def _assess(tb, s: int, t: float, wall: float) -> bool:
    """Assess slot ``s``'s segment as it is and use a confident model (the fit and what
    follows from it: the budget's cost); False if it holds too little to fit."""
    st: IdState = tb.ident[s]
    n = int(tb.rec_n[s])
    data = tb.recorder.data[tb.rec[s], :, :n]
    starts = [a for a in st.starts if a < n]
    if len(starts) < identify.MIN_EVENTS or n < identify.MIN_SAMPLES:
        return False
    # a warm start (the grid search otherwise): the model in force, else the last
    # confident one (a hinted loop's check; a hint-free loop's is in force)
    known = st.in_force or (st.model if st.model is not None and st.model.confident else None)
    start = None if known is None else (known.tau, known.theta)
    last = int(tb.rec_m[s])  # the samples the last row holds so far
    # a segment starts anew where op comes in the samples: sent now, sent throughout
    op_sent = bool(tb.prev_meas[s])
    refused = op_law.refusal(tb, s) if op_sent else None
    if refused is not None:  # a model from this op would be off by its factor
        st.model, st.why = None, refused
        return True
    result = identify.assess(
        data[0], data[1], data[2], data[3], starts, start, last, op_sent, _registered(tb, s)
    )
    st.events = result.events[-MAX_EVENTS:]
    st.model, st.why = result.model, result.why
    if result.model is not None and model_check.plant_moved(st.fallback, result.model):
        verify.forget_figures(tb, s)  # they are the plant of before's
    if result.model is not None and result.model.confident:
        if not refuted.declines(tb, s, result.model, t, wall):
            model_use.use(tb, s, result.model, t, wall)
    elif tb.scaled[s] and result.why.startswith(
        (identify.IMPRECISE, identify.DISAGREE, identify.INTEGRATING)
    ):
        model_use.envelope(tb, s, result.model, t, wall, sure=False)
    return True


def _registered(tb, s: int) -> float:
    """Slot ``s``'s registered sample period, s (foptd_fit.sample_period's check)."""
    return tb.configs[tb.ids[s]].sample_period_s


def catch_up(tb, wall: float) -> None:
    """Assess loops owed an assessment, one pass's worth of the identification budget,
    each on its segment as it is now (:mod:`service.engine.fit_budget`)."""
    fits = tb.fits
    fits.refill(wall)
    while fits.owed and fits.allows():
        s = fits.next_owed()
        if tb.rec[s] >= 0 and tb.watch[s]:  # (identification since turned off: nothing)
            n = int(tb.rec_n[s])
            tb.fits.timed(_assess, tb, s, float(tb.last_t[s]), wall)
            _trim(tb, s, n)


def closely(tb, s: int) -> bool:
    """Whether a loop is assessed at every chance (each event close and during events)
    rather than at every :data:`CHECK_EVERY` th close: no confident model yet, flagged,
    paused (but as integrating), or the latest model drifted from the one in force by more than
    :data:`DRIFT` in K or tau (a plant on the move is caught before it leaves the box).
    A loop tuned on its registered hint is assessed at each event close only: the check
    of a hint is not urgent, and the fits are the engine's main cost."""
    st: IdState = tb.ident[s]
    m, known = st.model, st.in_force
    if tb.out_env[s] and m is not None and m.integrating:
        return False  # (no model comes to resume it while the process integrates)
    if tb.mismatch[s] or tb.out_env[s]:
        return True
    if known is None and tb.scaled[s]:
        return False
    if m is None or not m.confident:
        return True
    if known is None:
        return False
    off = max(abs(math.log(m.k / known.k)), abs(math.log(m.tau / known.tau)))
    return off > math.log(DRIFT)


def _trim(tb, s: int, n: int) -> None:
    if len(tb.ident[s].starts) > MAX_EVENTS:
        _drop_oldest(tb, s, n)


def _drop_oldest(tb, s: int, n: int) -> None:
    """Forget the oldest event of the segment's ``n`` rows (keeping the row before the
    next move)."""
    st: IdState = tb.ident[s]
    cut = st.starts[1] - 1
    data = tb.recorder.data[tb.rec[s]]
    data[:, : n - cut] = data[:, cut:n]
    tb.rec_n[s] = n - cut
    st.starts = [a - cut for a in st.starts[1:]]
    tb.rec_ev[s] -= cut


def stop(tb, s: int) -> None:
    """Drop a loop's open segment (removal, a new identification)."""
    tb.fits.forget(s)
    if tb.rec[s] >= 0:
        tb.recorder.give(int(tb.rec[s]))
        tb.rec[s] = -1
    if tb.ident[s] is not None:
        tb.ident[s].starts = []


REFUTED = (
    "the identified model's tuning rang and was rolled back: identification restarted "
    "(a model like it is not used again)"
)
"""Why a loop identifies again after :data:`service.engine.verify.REFUTING` verdicts."""


def restart(
    tb, s: int, wall: float, actor: str = "", why: str = "", keep: Sequence[Refuted] = ()
) -> None:
    """Identify again from scratch (``POST /loops/{id}/identify``, or ``why`` the engine's
    own reason): the identified scaling is dropped (a hint-free loop is 'identifying'
    again, a hinted one back on its hint), flags cleared, the open segment discarded, the
    bounds back to the configured ones, the models refuted on the loop forgotten but
    ``keep`` (the engine's restart after a refutation keeps them:
    :mod:`service.engine.refuted`); ``actor`` (who asked) in the audit row's detail as a
    reset's.

    Where the scaling in force changes, what was measured in it starts again
    (:func:`~service.engine.model_use.new_scaling`: the episode, the decimation window,
    the open setpoint response) and the last-good gains' figures go (they were measured
    over the old RL periods, maybe on a plant that changed: the next response is a
    baseline, as after registration). A change pending stays pending: no response is
    judged while the loop has no scaling, and the first complete one under the scaling
    then in force judges it with the changes made since (a hint-free loop's tuning from
    its new model); an oscillation still fails it at once."""
    before = tb.scaling_of(s)
    stop(tb, s)
    tb.ident[s] = IdState(why=why or "identification restarted", refuted=keep)
    tb.mismatch[s] = tb.out_env[s] = False
    tb.reconfigure(tb.configs[tb.ids[s]])
    t = tb.last_t[s]
    if tb.scaling_of(s) != before:
        model_use.new_scaling(tb, s, float(t))
        verify.forget_figures(tb, s)
    detail = f"restarted; actor={actor}" if actor else f"restarted: {why}" if why else "restarted"
    model_use.audit(tb, s, None if math.isnan(t) else float(t), wall, "identify", detail)
