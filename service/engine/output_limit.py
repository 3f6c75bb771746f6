"""A controller output held at a limit, seen in the data (a valve fully open or shut).

The gateway's ``saturated`` flag says so where the DCS exposes it; many maps have no such
point (an OPC UA server with the block's OUT but no limit flag), yet send the output
``op``. A PI in auto moves its output at every sample its error is not zero: the integral
term by ki e dt, the proportional one by kp times the error's change. An output that
stays where it is, sample after sample, while that law would have moved it by a visible
share of its range, is not being moved by the PI: it is clamped at a limit of its range
(or by the DCS's anti-windup, or held by a tracking mode). The loop is then treated as
one the gateway flags saturated (status ``saturated``: no RL step, the error not
integrated, identification's segment ended, the monitor's saturated share), from the
sample that shows it until the first sample whose output moves.

The rule, per loop, on accepted samples in auto that carry ``op`` and no flag:

* a *run* is the samples since the output last moved by more than :data:`OP_RTOL` of its
  scale (the largest of its magnitude and the range of outputs seen);
* over the run the PI law's change of the output is summed from the error and the gains
  in force (those the sample reports, else the tuner's), P on the error and I by the
  trapezoid: its form (P on the PV, an ideal or series PI) changes the P part only
  where the setpoint moves, and by no more than the move;
* the output is held once the run has :data:`HELD_SAMPLES` samples and that change is at
  least :data:`HELD_SHARE` of the scale; it stays held until the output moves.

Neither clause alone: a converged loop's output moves by less than the tolerance while
the law agrees (its change is as small), and a gateway that samples faster than the DCS
executes its PI, or reports the output through a deadband or in whole percent, sees it
still for a few samples while the law has it move by less than the quantum. A gateway
whose ``op`` is the valve's position feedback rather than the PI's output is read the
same way: a stuck valve shows as held too.

Without ``op`` (the output reconstructed from the law follows it by construction) the
sign is in the PV: a PI at a limit keeps asking for more output, and the PV does not
follow. The rule, per loop with a scaling, on accepted samples in auto without ``op`` or
flag, with a setpoint (:func:`_pv_rule`; agent units):

* a *run* is the samples since the filtered error (:data:`FILTER`) left the band
  :data:`BAND` with one sign, under one setpoint; it is cut into *blocks* as long as the
  longest lag tau + theta in the agent's envelope (:data:`BLOCK`);
* at each block's end, the PI law's push over the block before (P on the filtered error,
  I by the trapezoid, with the gains the sample reports, else the tuner's) is what the
  PV should have followed by now: at least :data:`SHARE` of it times the envelope's
  lowest gain (:data:`LOW_GAIN`) toward the setpoint. The block *stalls* where that
  stands :data:`NOISE_SIGMAS` standard deviations out of the filtered error's noise
  and the PV moved less than :data:`FOLLOW` of it;
* the PV is *stalled* (the loop treated as saturated, as above) from the
  :data:`STALLS`-th stalled block in a row until a block that is not, or the run's end.

A linear loop inside the envelope cannot stall: the law's push reaches its PV within the
next block. What can: a valve at a limit, a stuck valve or transmitter, a loop far
outside the envelope (its lag beyond :data:`BLOCK`, its gain below :data:`LOW_GAIN`), and
a load ramping against the law at the rate the law pushes (a steady offset, the output
moving) for two blocks: that needs a load moving the PV by more than a typical setpoint
move every block (docs/identification.md, *An output held at a limit*).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import orjson

from service.engine import box
from service.engine.audit import audit_row
from service.engine.updates import MODE_VALUES

if TYPE_CHECKING:
    from service.engine.table import LoopTable

OP_RTOL = 1e-6
"""An output within this share of its scale of the run's first is unchanged (a DCS
reports a clamped output exactly; float32 storage moves it by 6e-8 of itself)."""
HELD_SAMPLES = 20
"""Samples a run lasts at least before the output counts as held: a gateway polling a
few times per execution of the DCS's PI sees its output still between executions."""
HELD_SHARE = 0.05
"""The PI law's change over the run, as a share of the output's scale, beyond which a
still output is held: above the quantum of an output reported in whole percent or
through an OPC UA deadband of a few percent, far below what an error that persists
with the output at a limit builds up (the integral grows without bound)."""
SCALE_FLOOR = 1e-9
"""The output's scale while it has only been seen at 0 (a valve shut from the first
sample): any change the law asks for then counts."""

BAND = 0.2
"""Filtered error (agent units: a tenth of the paper's move of 2) from which a run of the
PV rule starts; it ends below half of it, or at a change of the error's sign."""
BLOCK = (
    box.TRAINING_BOX["tau"][1]
    * box.ENVELOPE_MARGIN
    * (1.0 + box.TRAINING_BOX["theta_ratio"][1] * box.ENVELOPE_MARGIN)
)
"""The PV rule's block (agent time units): the longest lag tau + theta in the envelope
(3.75; 1.4 RL periods, 7.5 time constants of the hint's)."""
LOW_GAIN = box.TRAINING_BOX["gain"][0] / box.ENVELOPE_MARGIN
"""The lowest gain in the envelope (agent units): a third of the hint's."""
FILTER = 0.25
"""Time constant of the error's filter, as a share of the block."""
SHARE = 0.5
"""Share of a block's push that reaches the PV by the next block's end: a pure dead time
of one block passes all of it, a first-order lag of one block 77 %."""
FOLLOW = 0.25
"""The PV stalls where it moved toward the setpoint by less than this share of what it
should have."""
NOISE_SIGMAS = 4.0
"""The PV's expected move must stand this many standard deviations of the filtered
error's change over a block above nothing."""
STALLS = 2
"""Stalled blocks in a row that make the PV stalled (one is a load step's departure)."""
NOISE_WEIGHT = 0.01
"""Weight of a sample in the running estimate of the error's noise variance."""

F64 = (
    "oh_op", "oh_n", "oh_law", "oh_lo", "oh_hi",
    "ps_sign", "ps_sp", "ps_t0", "ps_ef", "ps_ef0", "ps_push", "ps_prev", "ps_nv",
    "ps_stalls",
)  # fmt: skip
"""Per loop: the op rule's run's output (NaN: no run), its samples, the PI law's change
over it, the lowest and highest output seen; the PV rule's run's sign (0: no run) and
setpoint, its block's start (s), the filtered error (agent units) now and at the block's
start, the law's push over the block and over the one before (agent output units; NaN:
none yet), the error's noise variance (agent units^2, NaN: none yet) and the stalled
blocks in a row."""
BOOL = ("oh_held", "ps_held")
"""Per loop: the output is held (the loop counts as saturated); the PV is stalled (so too)."""
CLEAR = {
    "oh_op": math.nan, "oh_n": 0.0, "oh_law": 0.0, "oh_lo": math.nan, "oh_hi": math.nan,
    "oh_held": False,
    "ps_sign": 0.0, "ps_sp": math.nan, "ps_t0": math.nan, "ps_ef": 0.0, "ps_ef0": 0.0,
    "ps_push": 0.0, "ps_prev": math.nan, "ps_nv": math.nan, "ps_stalls": 0.0,
    "ps_held": False,
}  # fmt: skip
"""Each array's value with no run and no output seen (a new loop; a snapshot from before
the rule)."""


def clear(tb: LoopTable, s) -> None:
    """No run, no output seen (a new loop)."""
    for name, value in CLEAR.items():
        getattr(tb, name)[s] = value


def end_runs(tb: LoopTable, s) -> None:
    """No run of either rule (in manual, flagged, a new episode): nothing held."""
    _end_op_runs(tb, s)
    _end_pv_runs(tb, s)


def _end_op_runs(tb: LoopTable, s) -> None:
    tb.oh_op[s] = math.nan
    tb.oh_n[s] = tb.oh_law[s] = 0.0
    tb.oh_held[s] = False


def _end_pv_runs(tb: LoopTable, s) -> None:
    tb.ps_sign[s] = tb.ps_stalls[s] = 0.0
    tb.ps_held[s] = False


def scale(tb: LoopTable, slots) -> np.ndarray:
    """The output's scale (its units): the largest of its run's magnitude and its range."""
    return np.maximum(
        np.fmax(np.abs(tb.oh_op[slots]), tb.oh_hi[slots] - tb.oh_lo[slots]), SCALE_FLOOR
    )


def observe(
    tb: LoopTable, slots: np.ndarray, cols: dict[str, np.ndarray], last_t: np.ndarray,
    gap: np.ndarray, wall: float,
) -> np.ndarray:  # fmt: skip
    """Take accepted samples of distinct loops (before ``last_e`` moves on; ``cols`` as
    :func:`service.engine.rules.ingest` holds them, e sign-adjusted; ``gap``: a first
    sample, a new clock or a stale gap). Returns where the output is held, seen in
    ``op`` or in the PV; a hold that begins is counted and audited (reason
    ``output_held``, the detail's ``seen``: ``op`` or ``pv``)."""
    kp = np.where(np.isnan(cols["kp"]), tb.kp[slots], cols["kp"])
    ki = np.where(np.isnan(cols["ki"]), tb.ki[slots], cols["ki"])
    free = cols["auto"] & ~cols["saturated"]
    sent = ~np.isnan(cols["op"])
    held = _op_rule(tb, slots, cols, last_t, gap, wall, free & sent, kp, ki)
    return held | _pv_rule(tb, slots, cols, last_t, gap, wall, free & ~sent, kp, ki)


def _op_rule(tb, slots, cols, last_t, gap, wall, usable, kp, ki) -> np.ndarray:
    """:func:`observe`'s rule on ``op``, for the samples ``usable`` (in auto, unflagged,
    with ``op``)."""
    op, e, t = cols["op"], cols["e"], cols["t"]
    if not usable.any():  # the usual case of gateways that send no op: one test
        running = ~np.isnan(tb.oh_op[slots])
        if running.any():
            _end_op_runs(tb, slots[running])
        return np.zeros(slots.size, bool)
    was = tb.oh_held[slots]
    tb.oh_lo[slots] = np.where(usable, np.fmin(tb.oh_lo[slots], op), tb.oh_lo[slots])
    tb.oh_hi[slots] = np.where(usable, np.fmax(tb.oh_hi[slots], op), tb.oh_hi[slots])
    ref, size = tb.oh_op[slots], scale(tb, slots)  # a run's scale: its output's and range's
    same = usable & ~gap & (np.abs(op - ref) <= OP_RTOL * size)  # NaN ref: False
    last_e = tb.last_e[slots]
    with np.errstate(invalid="ignore"):
        law = kp * (e - last_e) + ki * 0.5 * (e + last_e) * (t - last_t)
    tb.oh_law[slots] = np.where(same, tb.oh_law[slots] + law, 0.0)
    tb.oh_n[slots] = np.where(same, tb.oh_n[slots] + 1.0, 0.0)
    tb.oh_op[slots] = np.where(same, ref, np.where(usable, op, math.nan))
    held = same & (
        was | ((tb.oh_n[slots] >= HELD_SAMPLES) & (np.abs(tb.oh_law[slots]) >= HELD_SHARE * size))
    )
    tb.oh_held[slots] = held
    for i in np.flatnonzero(held & ~was).tolist():
        s = int(slots[i])
        _audit(tb, s, float(t[i]), wall, {
            "seen": "op", "op": float(op[i]), "samples": int(tb.oh_n[s]),
            "law_change": float(tb.oh_law[s]),
            "op_range": [float(tb.oh_lo[s]), float(tb.oh_hi[s])],
        })  # fmt: skip
    return held


def _pv_rule(tb, slots, cols, last_t, gap, wall, usable, kp, ki) -> np.ndarray:
    """:func:`observe`'s rule on the PV (module docstring), for the samples ``usable`` (in
    auto, unflagged, without ``op``) of loops with a scaling."""
    usable = usable & tb.scaled[slots]
    if not usable.any():  # no run, and the next usable sample starts afresh
        tb.ps_ef[slots], tb.ps_push[slots], tb.ps_sp[slots] = 0.0, 0.0, math.nan
        running = tb.ps_sign[slots] != 0.0
        if running.any():
            _end_pv_runs(tb, slots[running])
        return np.zeros(slots.size, bool)
    e, t, sp = cols["e"], cols["t"], cols["sp"]
    es, us, block = tb.e_scale[slots], tb.u_scale[slots], BLOCK * tb.time_unit[slots]
    ea, last_ea = e * es, tb.last_e[slots] * es
    dt = np.where(gap, 0.0, t - last_t)
    same_sp = usable & ~gap & (sp == tb.ps_sp[slots])
    alpha = np.where(same_sp, np.minimum(1.0, dt / (FILTER * block)), 1.0)
    ef = np.where(usable, tb.ps_ef[slots] + alpha * (ea - tb.ps_ef[slots]), 0.0)
    # the noise variance of one sample: half the mean square change between samples
    change = (ea - last_ea) * (ea - last_ea) / 2.0
    nv = tb.ps_nv[slots]
    nv = np.where(same_sp, np.where(np.isnan(nv), change, nv + NOISE_WEIGHT * (change - nv)), nv)
    tb.ps_nv[slots] = nv
    sign = tb.ps_sign[slots]
    on = same_sp & (sign != 0.0) & (np.sign(ef) == sign) & (np.abs(ef) >= 0.5 * BAND)
    with np.errstate(invalid="ignore"):
        push = tb.ps_push[slots] + ki * 0.5 * (e + tb.last_e[slots]) * dt * us
    push = np.where(on, push, 0.0)
    tb.ps_ef[slots] = ef
    tb.ps_sp[slots] = np.where(usable, sp, math.nan)
    ended = ~on & (sign != 0.0)
    if ended.any():
        _end_pv_runs(tb, slots[ended])
    start = usable & ~on & (np.abs(ef) >= BAND)
    if start.any():  # a run starts: its first block, none before it
        tb.ps_sign[slots[start]] = np.sign(ef[start])
        tb.ps_t0[slots[start]], tb.ps_ef0[slots[start]] = t[start], ef[start]
        tb.ps_prev[slots[start]] = math.nan
    # a block's end: judged on the block before's push, and the next block begins
    close = on & (t - tb.ps_t0[slots] >= block)
    if close.any():
        c, sc = np.flatnonzero(close), slots[close]
        sg, ef0 = tb.ps_sign[sc], tb.ps_ef0[sc]
        push[c] += kp[c] * (ef[c] - ef0) / es[c] * us[c]
        expected = SHARE * LOW_GAIN * sg * tb.ps_prev[sc]  # NaN: the run's first block
        moved = sg * (ef0 - ef[c])
        # two filtered errors a block apart, each of variance nv alpha / 2 (alpha: dt over
        # the filter's time): their difference's variance is nv alpha
        sd = np.sqrt(np.maximum(nv[c], 0.0) * dt[c] / (FILTER * block[c]))
        with np.errstate(invalid="ignore"):
            stalled = (expected >= NOISE_SIGMAS * sd) & (moved < FOLLOW * expected)
        was = tb.ps_held[sc]
        tb.ps_stalls[sc] = np.where(stalled, tb.ps_stalls[sc] + 1.0, 0.0)
        tb.ps_held[sc] = tb.ps_stalls[sc] >= STALLS
        tb.ps_prev[sc], tb.ps_ef0[sc], tb.ps_t0[sc] = push[c], ef[c], t[c]
        push[c] = 0.0
        for k in np.flatnonzero(tb.ps_held[sc] & ~was).tolist():
            i, s = int(c[k]), int(sc[k])
            _audit(tb, s, float(t[i]), wall, {
                "seen": "pv", "error": float(ef[i] / es[i]), "block_s": float(block[i]),
                "expected_pv": float(expected[k] / es[i]), "moved_pv": float(moved[k] / es[i]),
            })  # fmt: skip
    tb.ps_push[slots] = push
    return tb.ps_held[slots] & on


def _audit(tb: LoopTable, s: int, t: float, wall: float, detail: dict) -> None:
    tb.n_held[s] += 1
    gains = (float(tb.kp[s]), float(tb.ki[s]))
    tb._audit.append(
        audit_row(tb.ids[s], wall, t, int(tb.seq[s]), MODE_VALUES[tb.mode[s]],
                  "output_held", gains, gains, orjson.dumps(detail).decode())
    )  # fmt: skip
