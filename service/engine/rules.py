"""The sample rules, vectorised over many loops: the one implementation.

For each accepted sample the engine integrates the error (trapezoid on the plant's
timestamps), decimates to the RL period by sample time (never wall time, so an
accelerated simulation tunes as fast as it publishes) and says whether the loop is due
for an RL step (:mod:`service.engine.stepping` then steps it).

* A sample is rejected as a flood (over the per-loop rate, wall clock), a duplicate or
  out of order (plant clock; a run of :data:`CLOCK_RESET_SAMPLES` consistent older
  samples is taken as a new plant clock instead), or absurd (an error beyond
  :data:`MAX_AGENT_ERROR` agent units). A rejected sample changes nothing of its loop.
* No RL step while the gateway reports manual mode or a saturated output (or the data
  show the output held at a limit: :mod:`service.engine.output_limit`), and none
  across a gap of more than ``stale_periods`` sample periods (the decimation window
  restarts at the first sample after the gap, and the integral does not bridge it).
  Nor is the error integrated while in manual or saturated (training never saw an
  integral wound up by an error nobody controls), and the decimation window restarts
  at the first sample back in auto, so a step sees a full RL period of control.
* ``frozen`` loops are never stepped, nor any loop while the plant is held
  (:mod:`service.engine.plant_hold`), nor loops without a scaling (identifying: their
  RL period is unknown, so they never fall due, nor on a window left from before
  identification restarted) or paused as out of the agent's envelope.
* Identification (:mod:`service.engine.watch`): samples with sp and pv are recorded in
  segments that open at setpoint moves; each move closes an event and assesses the
  segment, which may put a model in force (see that module).
* Excitation gate: the agent learns from setpoint responses, and stepped on a loop
  whose setpoint stands still it walks the gains far from where they were (see the
  evaluation's quiet-loop line). A loop is stepped only in RL periods that end within
  ``excitation_periods`` RL periods of a setpoint change of at least
  ``excitation_min_step`` (agent units; for gateways that send only the error, a jump
  of the error between two samples). Other periods leave the gains and the hidden
  state untouched and count as ``quiet``.
* Gains the gateway reports in a sample are adopted when they differ from the tuner's
  (an operator changed them), except when they are exactly the gains an auto update
  just replaced: then the update is still in flight and adopting would undo it. An
  ``auto`` loop's sample that says which update the DCS applied (``applied_seq``) is
  judged by it instead: below the loop's seq the gateway lags (nothing adopted, the
  update stays pending); equal, gains that differ are an operator's change (adopted)
  and equal ones confirm the update; above the seq, the rule without it.

The functions take the :class:`~service.engine.table.LoopTable` whose arrays they
update; a scalar statement of the same rules, one sample at a time, is kept in the tests
as the specification this module is checked against.
"""

from __future__ import annotations

import math

import numpy as np

from service.engine import (
    first_tuning,
    monitor,
    oscillation,
    output_limit,
    reported,
    steady,
    verify,
    watch,
)
from service.engine.audit import audit_row
from service.engine.modes import _MODES, AUTO, FROZEN
from service.engine.table import LoopTable
from service.units import error_window, ramp_gated, ramp_rule, track_moves, window_error
from service.wire.decode import Columns
from service.wire.protocol import RejectReason

MAX_AGENT_ERROR = 100.0
"""An error beyond this many agent units (training sees about 2) is an absurd sample."""
CLOCK_RESET_SAMPLES = 10
"""Consecutive, mutually increasing samples older than the loop's last one that are
taken as a new plant clock (a restarted gateway, or a last sample from the far future)
rather than rejected forever as out of order."""
EXCITATION_NOISE_SIGMAS = 5.0
"""A setpoint move opens the excitation gate only when it is at least this many measured
noise sigmas (the monitor's estimate), as well as ``excitation_min_step``; a jump of the
error of a loop sending only e, this many sigmas of the difference of two noisy samples
(sqrt 2 sigma). A response to a move buried in the noise teaches the agent nothing, and
its observation, scaled up by 2 / move, would be mostly noise; for e-only loops noise
alone otherwise opens the gate (sigma 0.05 agent units: in half of all RL periods). The
estimate counts once warm, for e-only loops from the start
(:func:`service.engine.oscillation.noise_sigma`)."""
GAIN_RTOL = monitor.GAIN_RTOL
"""Relative tolerance when comparing reported gains with the tuner's: a DCS storing gains
as float32 reports them off by up to 6e-8 relative, which is no operator's change."""


CLOCKED = (
    "excited_until", "move_t", "ramp_t", "ramp_from",  # the excitation gate, the ramp rule
    "cool_until", "x_until", "osc_until", "osc_seen", "g_osc",  # holds, oscillations seen
    "o_tc", "o_seen", "o_z", "o_zs",  # the oscillation detector
    "f_t", "ps_t0",  # the last response's end, the PV rule's block
    "mc_since",  # the model check's run of held steps (views.hold)
)  # fmt: skip
"""The plant times a loop keeps (beyond the one sample before), moved with a new plant
clock (a gateway restarted from 0): a hold left on the old clock would last as long as the
old clock had run. (An open response is dropped at the clock's gap: monitor.observe.)"""


def new_clock(tb: LoopTable, s: int, t: float) -> bool:
    """Count a run of consistent out-of-order samples; True when it is a new clock."""
    run = tb.back_n[s] + 1.0 if tb.back_n[s] and t > tb.back_t[s] else 1.0
    tb.back_t[s] = t
    tb.back_n[s] = 0.0 if run >= CLOCK_RESET_SAMPLES else run
    return run >= CLOCK_RESET_SAMPLES


def ingest(
    tb: LoopTable, slots: np.ndarray, rows: Columns, wall: float
) -> tuple[np.ndarray, list[tuple[int, RejectReason, str]]]:
    """Take decoded samples of *distinct* loops (``slots`` aligned with ``rows``).

    The one implementation of the sample rules, vectorised: flood limit, duplicate and
    out-of-order times (or a new plant clock), absurd errors, adoption of reported
    gains, the excitation gate, the error integral and decimation to the RL period.
    Returns (mask of the loops now due for an RL step, rejections as (row, reason,
    detail)); a rejected sample changes nothing of its loop but its counters.
    """
    cols = {k: getattr(rows, k) for k in ("t", "e", "sp", "kp", "ki", "auto", "saturated")}
    # a direct-acting loop is seen with its PV and SP negated: a positive-gain plant
    sign = tb.sign[slots]
    cols["e"], cols["sp"] = cols["e"] * sign, cols["sp"] * sign
    cols["op"] = rows.op if rows.op is not None else np.full(len(rows), math.nan)
    seqs = rows.applied_seq
    cols["applied_seq"] = seqs if seqs is not None else np.full(len(rows), -1, np.int64)
    t, e = cols["t"], cols["e"]
    now = steady.now(tb, wall)  # (a wall clock stepped back: see service.engine.steady)
    # a clock stepped back (no step-free one) refills nothing, and locks no loop out either
    elapsed = np.maximum(now - tb.token_wall[slots], 0.0)
    tokens = np.minimum(tb.burst, tb.tokens[slots] + elapsed * tb.rate)
    tb.token_wall[slots] = now
    flood = tokens < 1.0
    tb.tokens[slots] = np.where(flood, tokens, tokens - 1.0)
    last_t = tb.last_t[slots]
    dup = ~flood & (t == last_t)
    late = ~flood & (t < last_t)
    reclocked = []
    for i in np.flatnonzero(late).tolist():  # rare: a new plant clock, or rejected
        if new_clock(tb, int(slots[i]), float(t[i])):
            late[i] = False
            reclocked.append((i, last_t[i]))
            last_t[i] = math.nan
    absurd = ~(flood | dup | late) & (np.abs(e) * tb.e_scale[slots] > MAX_AGENT_ERROR)
    ok = ~(flood | dup | late | absurd)
    for i, old_t in reclocked:  # every time kept on the plant clock moves with it
        if ok[i]:
            for name in CLOCKED:
                getattr(tb, name)[slots[i]] += t[i] - old_t
    rejections: list[tuple[int, RejectReason, str]] = []
    if not ok.all():
        for i in np.flatnonzero(~ok).tolist():
            if flood[i]:
                rejections.append((i, RejectReason.flood, f"over {tb.rate:g} samples/s"))
            elif dup[i]:
                rejections.append((i, RejectReason.duplicate, f"t={t[i]} again"))
            elif late[i]:
                rejections.append((i, RejectReason.out_of_order, f"t={t[i]} < last t={last_t[i]}"))
            else:
                detail = f"|e|={abs(e[i]):g} is absurd for this loop"
                rejections.append((i, RejectReason.out_of_range, detail))
        slots, last_t, t, e = slots[ok], last_t[ok], t[ok], e[ok]
        cols = {k: v[ok] for k, v in cols.items()}
    tb.back_n[slots] = 0.0
    _adopt(tb, slots, cols, wall)
    # gains reported outside the bounds hold the loop (identification's output, steps)
    cols["held"] = reported.held(tb, slots)
    moved = _excite(tb, slots, cols, last_t)

    tb.n_samples[slots] += 1
    tb.last_wall[slots] = now
    gap = np.isnan(last_t) | (t - last_t > tb.stale_gap[slots])
    cols["saturated"] = cols["saturated"] | output_limit.observe(tb, slots, cols, last_t, gap, wall)
    auto, saturated = cols["auto"], cols["saturated"]
    paused = ~auto | saturated
    resumed = (tb.manual[slots] | tb.saturated[slots]) & ~paused
    tb.manual[slots] = ~auto
    tb.saturated[slots] = saturated
    tb.last_t[slots] = t
    fresh = gap | resumed
    watch.record(tb, slots, cols, last_t, gap, fresh, wall)
    first_tuning.flush(tb)  # the models put in force: one batched warm run
    if tb.monitoring:
        judged = monitor.observe(
            tb, slots, t, e, tb.last_e[slots], last_t, moved, fresh, gap, auto, saturated
        )
        if judged[0].size or judged[1].size:
            tb.to_judge.append(judged)
        verify.pause_oscillating(tb, slots, t, wall)
    period = tb.period[slots]
    next_due = np.where(fresh, t + period, tb.next_due[slots])
    step = np.where(fresh | paused, 0.0, 0.5 * (e + tb.last_e[slots]) * (t - last_t))
    tb.int_e[slots] += step * tb.int_scale[slots]
    tb.last_e[slots] = e
    total, count = error_window(
        e * tb.e_scale[slots], t, next_due, period,
        tb.win_sum[slots], tb.win_n[slots], tb.win_due[slots],
    )  # fmt: skip
    tb.win_sum[slots], tb.win_n[slots], tb.win_due[slots] = total, count, next_due
    reached = t >= next_due
    # the agent's error at the period's end, agent units
    obs_e = window_error(total, count, e * tb.e_scale[slots], next_due, period, tb.move_t[slots])
    tb.obs_e[slots[reached]] = obs_e[reached]
    next_due[reached] += period[reached] * (
        np.floor((t[reached] - next_due[reached]) / period[reached]) + 1.0
    )
    tb.next_due[slots] = next_due
    due_ok = reached & (tb.mode[slots] != FROZEN) & auto & ~saturated & ~tb.out_env[slots]
    due_ok &= tb.scaled[slots]  # (a window from before a restart of identification)
    due_ok &= ~verify.paused(tb, slots, t)  # the loop oscillates: neither stepped nor quiet
    due_ok &= ~cols["held"]  # gains reported outside the bounds: not ours to step
    due_ok &= not tb.hold.held  # the plant-wide hold (plant_hold.py): not stepped nor quiet
    ramp = ramp_gated(t, period, tb.ramp_t[slots], tb.ramp_from[slots], tb.sp_since[slots])
    gated = due_ok & (tb.gate_closed(slots, t) | ramp)
    tb.n_quiet[slots[gated]] += 1
    # held after a rollback or a rejected proposal (verify.py): neither stepped nor quiet
    due_ok &= ~gated & (t >= tb.cool_until[slots])
    due = np.zeros(ok.size, bool)
    due[np.flatnonzero(ok)[due_ok]] = True
    return due, rejections


def gate_step(tb: LoopTable, slots, has_sp) -> tuple[np.ndarray, np.ndarray]:
    """The excitation gate's smallest move (engineering units): ``excitation_min_step``
    or the noise rule's :data:`EXCITATION_NOISE_SIGMAS`, whichever is larger; and the
    noise rule's part alone (``quiet``'s why names the one that holds the gate)."""
    sigma = EXCITATION_NOISE_SIGMAS * oscillation.noise_sigma(tb, slots, cold=~has_sp)
    noise = np.where(has_sp, sigma, np.sqrt(2.0) * sigma)
    return np.maximum(tb.exc_step[slots], noise), noise


def _excite(tb: LoopTable, slots: np.ndarray, cols: dict[str, np.ndarray], last_t) -> np.ndarray:
    """The excitation gate's part of :meth:`ingest` (before ``last_e`` moves on); returns
    where the setpoint moved (the monitor's responses start there too). Also the ramp
    rule (:func:`service.units.ramp_rule`): ``cols["ramping"]``, where the sample's
    setpoint change continued a ramp (identification's too, service.engine.watch)."""
    sp, e, t = cols["sp"], cols["e"], cols["t"]
    has_sp = ~np.isnan(sp)
    # a loop sending only e: a setpoint change shows as a jump of e (and makes no runs)
    last_e = np.where(np.isnan(last_t), np.nan, tb.last_e[slots])
    m = track_moves(
        np.where(has_sp, sp, e),
        np.where(has_sp, tb.sp_ref[slots], last_e),
        tb.sp_anchor[slots],
        tb.move_t[slots],
        tb.obs_gain[slots],
        now=t,
        step=gate_step(tb, slots, has_sp)[0],
        run=np.where(has_sp, tb.period[slots], -np.inf),
        scale=tb.e_scale[slots],
    )
    r = ramp_rule(sp[:, None], tb.sp_last[slots], tb.sp_way[slots], tb.sp_since[slots])
    tb.sp_last[slots], tb.sp_way[slots], tb.sp_since[slots] = r.last, r.way, r.since
    ramping, starts = r.continues[:, 0], r.changed[:, 0] & ~r.continues[:, 0]
    tb.ramp_t[slots[ramping]], tb.ramp_from[slots[starts]] = t[ramping], t[starts]
    cols["ramping"] = ramping
    tb.sp_ref[slots] = np.where(has_sp, m.ref, tb.sp_ref[slots])
    tb.sp_anchor[slots], tb.move_t[slots], tb.obs_gain[slots] = m.anchor, m.last_move, m.gain
    # a setpoint that moves in manual or saturation (many DCSs track the PV with it)
    # excites nothing: the loop did not answer it (the references above still follow it)
    excites = m.moved & cols["auto"] & ~cols["saturated"]
    tb.excited_until[slots[excites]] = t[excites] + tb.exc_window[slots[excites]]
    return m.moved


def _adopt(tb: LoopTable, slots: np.ndarray, cols: dict[str, np.ndarray], wall: float) -> None:
    has_kp, has_ki = ~np.isnan(cols["kp"]), ~np.isnan(cols["ki"])
    report = has_kp | has_ki
    if not report.any():
        return
    slots, has_kp, has_ki = slots[report], has_kp[report], has_ki[report]
    cur_kp, cur_ki = tb.kp[slots], tb.ki[slots]
    kp = np.where(has_kp, cols["kp"][report], cur_kp)
    ki = np.where(has_ki, cols["ki"][report], cur_ki)
    same = _close(kp, cur_kp) & _close(ki, cur_ki)
    # an auto loop's applied_seq (-1: absent) says whether the gateway caught up with the
    # last auto update (auto_seq: advisory and shadow steps raise seq with nothing to
    # apply; after a restore, unknown: the seq)
    applied, auto = cols["applied_seq"][report], tb.mode[slots] == AUTO
    lags = auto & (applied >= 0) & (applied < tb.auto_seq[slots])
    current = auto & (applied == tb.seq[slots])
    in_flight = lags | (
        ~same
        & ~current
        & tb.pending[slots]
        & _close(kp, tb.prev_kp[slots])
        & _close(ki, tb.prev_ki[slots])
    )
    tb.pending[slots[~in_flight]] = False
    changed = np.flatnonzero(~same & ~in_flight)
    if not changed.size:
        return
    t = cols["t"][report]
    for i in changed.tolist():
        s = int(slots[i])
        old = (tb.kp[s], tb.ki[s])
        tb.kp[s], tb.ki[s] = kp[i], ki[i]
        verify.adopted(tb, s, old)
        tb._gains_dirty.add(s)
        tb._audit.append(
            audit_row(
                tb.ids[s], wall, float(t[i]), int(tb.seq[s]), _MODES[tb.mode[s]].value,
                "adopted", old, (float(kp[i]), float(ki[i])), adopted_detail(tb, s),
            )
        )  # fmt: skip


def adopted_detail(tb: LoopTable, s: int) -> str:
    """The audit detail of gains adopted from the gateway (in force in ``s`` now): said
    where they lie outside the guard's bounds, which no step of the tuner's would have
    left (an operator's deliberate choice, or samples that are not the DCS's)."""
    if not reported.outside(tb, s):
        return "gains reported by the gateway"
    lo, hi = (tb.c_kp_min[s], tb.c_ki_min[s]), (tb.c_kp_max[s], tb.c_ki_max[s])
    return (
        f"gains reported by the gateway, OUTSIDE the guard's bounds (kp {lo[0]:.6g} to"
        f" {hi[0]:.6g}, ki {lo[1]:.6g} to {hi[1]:.6g}): tuning held, status"
        " gains_out_of_bounds (are they the DCS's gains, in pitune's parallel form?)"
    )


def _close(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) <= GAIN_RTOL * np.maximum(np.abs(a), np.abs(b))
