"""Loop performance monitoring, vectorised over loops: figures computed from the samples
the engine already receives (no extra traffic), and the oscillation detector.

:func:`observe` runs inside :func:`service.engine.rules.ingest` for every batch of
accepted samples (distinct loops, aligned arrays) and keeps three things per loop:

* **The current setpoint response.** A setpoint move (the excitation gate's move: at
  least ``excitation_min_step`` pv_scales) of a settled loop (:data:`SETTLED_AT_MOVE`)
  opens a response; it is *complete* when the
  plant time passes ``RESPONSE_PERIODS`` RL periods after the move, *truncated* when
  another move comes first (truncated responses are not compared: their IAE covers a
  shorter time). Over the response the engine integrates |e| (IAE, trapezoid on the
  plant's timestamps), the overshoot past the new setpoint, the 10 % and 90 % times, the
  last time outside the settling band and the squared deviation from the paper's target
  trajectory (first order, time constant 2 tau, dead time theta of the loop's model: the
  identified one, else the hint with theta 0), in agent units. A complete response's
  figures (IAE normalised by the move, overshoot %, rise and settling times in seconds,
  tracking MSE) are kept, with the last :data:`HISTORY` of them in a ring.
* **A window** of about ``WINDOW_PERIODS`` RL periods (exponential forgetting on the
  plant's time): mean and variance of the error, the shares of time in manual and
  saturated, and the share of samples rejected.
* **The oscillation detector** (:mod:`service.engine.oscillation`).

Units: times in plant seconds, errors in engineering units unless stated; arrays (n,)
indexed by slot unless stated.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from service.engine import oscillation
from service.units import AGENT_TAU, RL_STEP_AGENT_UNITS

GAIN_RTOL = 1e-6
"""Relative tolerance of equal gains (the sample rules' ``GAIN_RTOL``; the rules import
this module, so the constant lives here and they import it)."""

if TYPE_CHECKING:
    from service.engine.table import LoopTable

RESPONSE_PERIODS = 2.0
"""A setpoint response is judged over this many RL periods after the move (11 hinted time
constants: the paper's target trajectory, time constant 2 tau, is within 0.4 % of the
new setpoint by then; the paper's setpoints move every 4 RL periods)."""
SETTLE_BAND = 0.05
"""Settling band, share of the move (5 %: a 2 % band sits inside 2 % noise)."""
SETTLED_AT_MOVE = 0.2
"""A move opens a response only if the error just before it was within this share of
the move (plus 3 noise sigmas): from a loop still on its way, the IAE per unit move is
the last response's tail as much as this one's. A setpoint sent back before a sluggish
loop got far (irregular setpoints) left the loop a fifth of the move to go: its IAE per
unit move was a tenth of a settled response's, became the baseline, and every later good
change was rolled back to the sluggish gains (session 24: step-test MSE 0.455)."""
WINDOW_PERIODS = 5.0
"""Time constant of the window figures, RL periods (the excitation gate's window)."""
REJECT_FORGET = 0.01
"""Per-sample forgetting of the rejected share (about the last 100 samples)."""
HISTORY = 8
"""Complete responses kept per loop for ``GET /loops/{id}/performance``."""
HIST_FIELDS = ("t", "iae", "overshoot_pct", "rise_s", "settle_s", "mse")
"""Columns of the history ring (the ``f_`` arrays: t, iae, over, rise, settle, mse)."""
_UNJUDGED = ("c_cut", "c_cut_s", "c_early", "c_left")
"""The moves since the last complete response that judged nothing (counts, then figures)."""
_FIGURES = ("f_t", "f_iae", "f_over", "f_rise", "f_settle", "f_mse", "f_move")
"""The last complete response's figures (the history ring's columns, in order)."""
F64 = [
    # current response: start, end, 10 %/90 % times, last time outside the settling band,
    # gains and seq at the move (the gains the response judges: exact, a verdict makes
    # them the last-good gains)
    "r_t0", "r_end", "r_t10", "r_t90", "r_settle", "r_kp", "r_ki", "r_seq",
    # end of the last complete response
    "f_t",
]  # fmt: skip
"""Per-loop float64 arrays of the monitor: plant times (float32 would round a Unix time
to 2 minutes), gains and seqs."""
F32 = [
    # current response: signed move, IAE, squared tracking error (agent units^2 s),
    # overshoot (share of the move)
    "r_move", "r_iae", "r_sq", "r_over",
    # the target trajectory's model: dead time, closed-loop time constant (s)
    "m_theta", "m_tau_cl",
    # last complete response (f_move: its signed move; a sample may open the next one)
    "f_iae", "f_over", "f_rise", "f_settle", "f_mse", "f_move",
    # window: error mean and mean square, shares of time in manual / saturated, share of
    # samples rejected
    "w_mean", "w_sq", "w_manual", "w_sat", "w_rej",
    # since the last complete response: responses a move cut short and how long the last
    # ran (s); moves that opened none, the loop not settled from the one before, and the
    # share of its move the last one found left: the verification view says why no
    # change is judged (setpoints moving faster than the loop settles or is judged)
    "c_cut", "c_cut_s", "c_early", "c_left",
]  # fmt: skip
"""Per-loop float32 arrays of the monitor: figures and running sums (a figure needs 3
digits; 7 hold a few hundred samples' sum)."""


def allocate(tb: LoopTable, capacity: int, old: int) -> None:
    """Grow the monitor's arrays (and the oscillation detector's) to ``capacity`` slots,
    keeping the first ``old``."""
    for name, shape, dtype in (
        *((n, (), np.float64) for n in F64),
        *((n, (), np.float32) for n in F32),
        ("r_mixed", (), bool),
        ("f_hist", (HISTORY, len(HIST_FIELDS)), np.float32),
        ("f_hist_n", (), np.int8),
        *oscillation.ARRAYS,
    ):
        arr = np.zeros((capacity, *shape), dtype)
        if old:
            arr[:old] = getattr(tb, name)[:old]
        setattr(tb, name, arr)


def clear(tb: LoopTable, s: int) -> None:
    """A new loop (or a reset): no response open, figures unknown, windows empty."""
    for name in ("r_t0", "r_end", *_FIGURES):
        getattr(tb, name)[s] = math.nan
    for name in ("w_mean", "w_sq", "w_manual", "w_sat", "w_rej"):
        getattr(tb, name)[s] = 0.0
    forget_unjudged(tb, s)
    tb.f_hist_n[s] = 0
    oscillation.clear(tb, s)


def forget_unjudged(tb: LoopTable, s: int) -> None:
    """No moves that judged nothing (:data:`_UNJUDGED`): a new loop, or a new scaling (they
    were counted against the old one's RL period)."""
    tb.c_cut[s] = tb.c_early[s] = 0.0
    tb.c_cut_s[s] = tb.c_left[s] = math.nan


def configure(tb: LoopTable, s, tau_s, theta_s) -> None:
    """The model the target trajectory follows (seconds; NaN tau: no model yet); ``s``,
    ``tau_s`` and ``theta_s``: one slot and floats, or aligned arrays."""
    tb.m_tau_cl[s] = 2.0 * tau_s
    tb.m_theta[s] = theta_s


def hinted_tau(period_s: float) -> float:
    """The time constant a scaling's RL period stands for (the hint's tau_hat), s."""
    return period_s / RL_STEP_AGENT_UNITS * AGENT_TAU


def observe(
    tb: LoopTable,
    slots: np.ndarray,
    t: np.ndarray,
    e: np.ndarray,
    prev_e: np.ndarray,
    last_t: np.ndarray,
    moved: np.ndarray,
    fresh: np.ndarray,
    gap: np.ndarray,
    auto: np.ndarray,
    saturated: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Take accepted samples of distinct loops (aligned arrays; ``prev_e``, ``last_t``:
    the loop's previous sample, NaN if none; ``moved``: a setpoint move; ``fresh``: no
    usable previous sample: ``gap`` (none, or a stale gap) or back from manual or
    saturation). Returns (slots whose response just completed, slots that just started
    oscillating).

    A sample in manual or saturation (``paused``) ends the open response unjudged and
    opens none: what the loop does there is not the gains' doing alone (an operator's
    output, a valve at its limit), so no response figure may come of it (a response
    ending in manual was judged and rolled back, published in manual). A sample in manual
    (and the first back from it) also starts the oscillation count again; one in
    saturation does not: a limit cycle that reaches the valve's limits in each
    half-period is the gains' doing as much as one that stays inside them, and a count
    restarted at each limit never flagged it (session 41: a loop cycling at 6 crossings
    per 100 s, the valve at its limit in 5-14 of every 100 samples, showed
    ``oscillating: false`` for 1,100 s). A loop held at a limit makes no lobes.
    """
    paused = ~auto | saturated
    dt = np.where(fresh | np.isnan(last_t), 0.0, t - last_t)
    done = _close(tb, slots, t, moved, fresh | paused)
    opens = moved & ~paused
    before = np.where(fresh[opens], 0.0, prev_e[opens])
    move = e[opens] - before
    allowed = SETTLED_AT_MOVE * np.abs(move) + 3.0 * oscillation.noise_sigma(tb, slots[opens])
    settled = np.abs(before) <= allowed
    early = slots[opens][~settled]
    tb.c_early[early] += 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        tb.c_left[early] = np.abs(before[~settled] / move[~settled])
    _open(tb, slots[opens][settled], t[opens][settled], move[settled])
    _respond(tb, slots, t, e, prev_e, dt, moved)
    _window(tb, slots, e, dt, auto, saturated)
    # back from manual: the manual samples before were the detector's breaks (o_j)
    back = fresh & ~gap & tb.o_j[slots]
    breaks = moved | gap | back | ~auto
    step = np.where(gap | back, 0.0, t - last_t)
    osc = oscillation.detect(tb, slots, t, e, prev_e, step, breaks)
    return done, osc


def _close(tb: LoopTable, slots, t, moved, fresh) -> np.ndarray:
    """Close the responses a sample ends; keep the complete ones' figures. A response
    with a hole (``fresh``: a gap in the samples, or a sample in (or back from) manual or
    saturation) is dropped, as one a new move cuts short: its figures would judge part
    of it."""
    open_ = ~np.isnan(tb.r_t0[slots])
    complete = open_ & (t > tb.r_end[slots]) & ~fresh
    ending = open_ & (complete | moved | fresh)
    if not ending.any():
        return slots[:0]
    # a response during which the gains changed judges no gains alone: its figures
    # are kept, but it neither refreshes the last-good figure nor verifies (verify.py)
    cut = slots[ending & moved & ~complete & ~fresh]
    tb.c_cut[cut] += 1.0
    tb.c_cut_s[cut] = t[ending & moved & ~complete & ~fresh] - tb.r_t0[cut]
    end = slots[ending]
    tb.r_mixed[end] = ~(same_gains(tb.kp[end], tb.r_kp[end]) & same_gains(tb.ki[end], tb.r_ki[end]))
    done = slots[complete]
    if done.size:
        tb.c_cut[done] = tb.c_early[done] = 0.0
        move = np.abs(tb.r_move[done])
        t0, end = tb.r_t0[done], tb.r_end[done]
        # the ring's times are offsets from the newest response's end (float32 holds
        # them to the millisecond for a day; a Unix time it would round to 2 minutes)
        ring = tb.f_hist[done]
        ring[:, :, 0] += (tb.f_t[done] - end)[:, None]
        tb.f_t[done] = end
        tb.f_iae[done] = tb.r_iae[done] / move
        tb.f_over[done] = 100.0 * tb.r_over[done]
        tb.f_rise[done] = tb.r_t90[done] - tb.r_t10[done]
        settle = tb.r_settle[done] - t0
        tb.f_settle[done] = np.where(tb.r_settle[done] < tb.r_end[done] - 1e-9, settle, np.nan)
        tb.f_mse[done] = tb.r_sq[done] / (end - t0)
        tb.f_move[done] = tb.r_move[done]
        ring[:, 1:] = ring[:, :-1]
        ring[:, 0] = np.column_stack(
            [np.zeros(done.size), tb.f_iae[done], tb.f_over[done], tb.f_rise[done],
             tb.f_settle[done], tb.f_mse[done]]
        )  # fmt: skip
        tb.f_hist[done] = ring
        tb.f_hist_n[done] = np.minimum(tb.f_hist_n[done] + 1, HISTORY)
    tb.r_t0[slots[ending]] = math.nan
    return done


def _open(tb: LoopTable, slots: np.ndarray, t: np.ndarray, move: np.ndarray) -> None:
    if not slots.size:
        return
    move = move.astype(np.float32)  # as stored: a move float32 holds as 0 is no move
    tb.r_t0[slots], tb.r_move[slots] = t, np.where(move == 0.0, np.nan, move)
    tb.r_end[slots] = t + RESPONSE_PERIODS * tb.period[slots]
    tb.r_iae[slots] = tb.r_sq[slots] = tb.r_over[slots] = 0.0
    tb.r_t10[slots] = tb.r_t90[slots] = math.nan
    tb.r_settle[slots] = t
    tb.r_kp[slots], tb.r_ki[slots], tb.r_seq[slots] = tb.kp[slots], tb.ki[slots], tb.seq[slots]


def _respond(tb, slots, t, e, prev_e, dt, moved) -> None:
    """Accumulate the open responses' figures (the move's own sample opens, not adds)."""
    live = ~np.isnan(tb.r_t0[slots]) & ~moved & (dt > 0)
    if not live.any():
        return
    s, t, e, prev_e, dt = slots[live], t[live], e[live], prev_e[live], dt[live]
    move, t0 = tb.r_move[s], tb.r_t0[s]
    tb.r_iae[s] += 0.5 * (np.abs(e) + np.abs(prev_e)) * dt
    left = e / move  # share of the move still to go: 1 at the move, 0 on the setpoint
    tb.r_over[s] = np.maximum(tb.r_over[s], -left)
    first10 = np.isnan(tb.r_t10[s]) & (left <= 0.9)
    tb.r_t10[s[first10]] = t[first10]
    first90 = np.isnan(tb.r_t90[s]) & (left <= 0.1)
    tb.r_t90[s[first90]] = t[first90]
    outside = np.abs(left) > SETTLE_BAND
    tb.r_settle[s[outside]] = t[outside]
    with np.errstate(invalid="ignore", over="ignore"):
        since = t - t0 - tb.m_theta[s]
        target_e = move * np.where(since > 0, np.exp(-since / tb.m_tau_cl[s]), 1.0)
        err = (e - target_e) * tb.e_scale[s]
    tb.r_sq[s] += np.where(np.isfinite(err), err * err, 0.0) * dt


def _window(tb, slots, e, dt, auto, saturated) -> None:
    span = WINDOW_PERIODS * tb.period[slots]
    a = np.where(np.isfinite(span) & (span > 0), np.minimum(dt / span, 1.0), 0.0)
    tb.w_mean[slots] += a * (e - tb.w_mean[slots])
    tb.w_sq[slots] += a * (e * e - tb.w_sq[slots])
    tb.w_manual[slots] += a * (~auto - tb.w_manual[slots])
    tb.w_sat[slots] += a * (saturated - tb.w_sat[slots])
    tb.w_rej[slots] *= 1.0 - REJECT_FORGET


def rejected(tb: LoopTable, s: int) -> None:
    """A sample of loop ``s`` was rejected (the rejected share's other half)."""
    tb.w_rej[s] = tb.w_rej[s] * (1.0 - REJECT_FORGET) + REJECT_FORGET


def dumps(tb: LoopTable, slots: np.ndarray) -> list[dict]:
    """The last response's figures, the history ring and the moves left unjudged
    (:data:`_UNJUDGED`) of the loops at ``slots``, for the runtime snapshot (the open
    response and the windows restart after a restart: a gap ends them anyway), one dict
    each (NaN stays: the snapshot's orjson writes null); each array read once for all of
    them, the history only of loops that have one."""
    last = np.stack([getattr(tb, name)[slots] for name in _FIGURES], axis=1).tolist()
    kept = (tb.f_hist_n[slots] > 0).tolist()
    cut = np.stack([getattr(tb, name)[slots] for name in _UNJUDGED], axis=1).tolist()
    return [
        {"last": row, "hist": history(tb, s) if has else [], "cut": c}
        for row, s, has, c in zip(last, slots.tolist(), kept, cut, strict=True)
    ]


def history(tb: LoopTable, s: int) -> list[list[float]]:
    """Loop ``s``'s complete responses, newest first: rows of :data:`HIST_FIELDS`."""
    rows = tb.f_hist[s, : int(tb.f_hist_n[s])].astype(np.float64)
    rows[:, 0] += tb.f_t[s]
    return rows.tolist()


def load(tb: LoopTable, slots: np.ndarray, dicts: list[dict]) -> None:
    """The figures of snapshots (:func:`dumps`' dicts) into the loops at ``slots``: the
    last response's with one assignment per array, the history of those that have one."""
    lasts = [d.get("last") for d in dicts]
    has = [i for i, last in enumerate(lasts) if last]
    if has:  # (a snapshot from before f_move has one figure fewer: null)
        width = len(_FIGURES)
        columns = zip(*(lasts[i] + [None] * (width - len(lasts[i])) for i in has), strict=True)
        for name, values in zip(_FIGURES, columns, strict=True):
            put(getattr(tb, name), slots[has], list(values), math.nan)
    cut = [d.get("cut") or [0.0, None, 0.0, None] for d in dicts]  # (since session 40)
    for i, name in enumerate(_UNJUDGED):
        put(getattr(tb, name), slots, [c[i] for c in cut], 0.0 if i % 2 == 0 else math.nan)
    tb.f_hist_n[slots] = 0
    for s, d in zip(slots.tolist(), dicts, strict=True):
        hist = d.get("hist")
        if hist:
            n = min(len(hist), HISTORY)
            rows = np.array(hist[:n], dtype=np.float64)
            rows[:, 0] -= tb.f_t[s]
            tb.f_hist[s, :n] = rows
            tb.f_hist_n[s] = n


def same_gains(a, b) -> np.ndarray:
    """Equal gains, as the engine compares them (relative 1e-6: float32 DCS storage)."""
    return np.abs(a - b) <= GAIN_RTOL * np.maximum(np.abs(a), np.abs(b))  # arrays or floats


ABSENT = object()
"""A value a snapshot does not hold (see :func:`put`)."""


def put(arr: np.ndarray, slots: np.ndarray, values: list, default: float) -> None:
    """``values`` (aligned with ``slots``; None: ``default``, :data:`ABSENT`: left as it
    is) into ``arr`` at ``slots`` in one assignment."""
    if ABSENT in values:
        kept = [i for i, v in enumerate(values) if v is not ABSENT]
        slots, values = slots[kept], [values[i] for i in kept]
    arr[slots] = [default if v is None else v for v in values]
