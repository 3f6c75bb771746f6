"""The oscillation detector of the loop monitor, vectorised over loops.

Hägglund's idea (1995, "A control-loop performance monitor", Control Eng. Practice
3(11)) of splitting the error at its zero crossings and judging each half-period's IAE,
with the regularity test of Thornhill, Huang and Zhang (2003, "Detection of multiple
oscillations in control loops", J. Process Control 13(1)): the intervals between zero
crossings of a real oscillation are regular, ``r = mean(T) / (3 std(T)) > 1``. A loop
oscillates when either of two tests holds at a crossing of the hysteresis band (3 noise
sigmas):

* **sustained**: its last :data:`OSC_LOBES` half-periods are regular, the newest has a
  mean |e| above the band (the older ones above half of it: a growing oscillation's
  first lobes are still rising out of the noise), and the amplitude does not decay by
  more than :data:`OSC_DECAY` per period;
* **growing**: its last two half-periods are regular and span at least
  :data:`OSC_GROWTH_SAMPLES` samples each, the newer lobe's mean |e| is above the band
  and at least :data:`OSC_GROWTH` times the older one's, the older one's above half the
  band, and with a third lobe on record the newest is not smaller than the one a period
  before (an unstable loop's lobes grow; a stable loop's free response decays, so two
  lobes suffice where three are needed for a sustained oscillation).

Rules that make the verdict come early (measured: ``pitune verify-eval``,
docs/tuner.md):

- a lobe that leaves the band from inside it is whole (the half-period from that exit
  to the next crossing is the one from crossing to crossing); only the first lobe after
  a setpoint move or a gap is partial and not on record;
- a lobe whose error came back into the band and across zero, and leaves the band again
  on the same side, starts again there: the half-cycle between stayed inside the band
  (an oscillation riding on an offset, whose one side rises out of the noise first), and
  the lobe from the first exit would be long and its mean |e| diluted;
- the oldest lobe judged may have begun before the oscillation did (noise carried the
  error out of the band first, then the oscillation grew inside the lobe): when it is
  longer than the newer ones its length is no irregularity and its mean |e|, diluted by
  the time before, is not held against the band (the decay test still uses it);
- the noise estimate is not frozen during its first :data:`NOISE_WARM` samples and the
  detector does not judge before (at startup the band is its floor, noise alone crosses
  it, and the lobes it makes would freeze the estimate low);
- a move's partial lobe that came back into the band and leaves it again on the same
  side is whole from there (an oscillation growing out of the move's tail);
- lobes that grow one after the other (an unstable loop) need no oldest lobe above
  half the band.

The period reported with a verdict (:func:`period`) is measured between the error's
zero crossings (the last one before each lobe left the band, interpolated), not between
the band crossings, which a growing oscillation's rising amplitude makes short by up to
a quarter period (the regularity tests keep the band crossings: the zero crossings'
more regular intervals flagged more stable loops).

Units: times in plant seconds, errors in engineering units; arrays (n,) indexed by slot
unless stated.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from service.engine.table import LoopTable

OSC_LOBES = 3
"""Half-periods judged by the sustained test."""
OSC_DECAY = 0.5
"""A lobe at least this share of the same-sign lobe one period earlier is not decaying
(a quarter-decay response, 0.25, is not an oscillation; a sustained one is 1)."""
OSC_GROWTH = 1.4
"""The growing test: the newer of two lobes has at least this times the older one's mean
|e|. A stable loop's next lobe is smaller than the last, but noise adds to or takes from
either: at 1.25 the stable loops tuned hard (kp 0.6 Ku) were flagged 14 more times in
300 (``pitune verify-eval --aggressive``), at 1.4 not once more (docs/tuner.md)."""
OSC_GROWTH_SAMPLES = 4.0
"""The growing test's lobes span at least this many sample intervals: two lobes of 2-3
samples are as often noise (one alarm on a stable loop in the evaluation), and the
fastest oscillations the sustained test catches in time anyway."""
OSC_NOISE_SIGMAS = 3.0
"""Hysteresis band of the zero crossings, noise sigmas."""
OSC_MIN_BAND = 0.01
"""Smallest band, agent units (1 % of pv_scale): a noiseless loop's rounding is not a lobe."""
NOISE_FORGET = 0.02
"""Per-sample forgetting of the noise variance, estimated from second differences of the
error (sigma^2 = E[d2^2] / 6 for white noise; a running mean over the first 50 samples):
blind to the loop's own slow motion, so neither a transient nor a growing oscillation
inflates the band. Not updated across a setpoint move, nor while two lobes of a
possible oscillation are on record."""
NOISE_WARM = round(1.0 / NOISE_FORGET)
"""Samples the noise estimate takes before the detector may judge (its running mean's
length; the estimate restarts after a restart)."""
OSC_MIN_SAMPLES = 2.0
"""A half-period spans at least this many sample intervals (shorter: noise)."""

F64 = ["o_tc", "o_seen", "o_z", "o_zs"]
"""Per-loop float64 plant times: the last band crossing, the last time the error was
outside the band, the error's last zero crossing, and the zero crossing that began the
current lobe."""
F32 = ["o_var", "o_sign", "o_iae", "o_index", "o_e2", "o_per"]
"""Per-loop float32: noise variance, sign of the current lobe, IAE since the last
crossing, the regularity index r, the error two samples back (the noise estimate's
second difference: float32 holds one up to 10^4 times the noise), the period measured
when the loop was last flagged (s)."""
RINGS = ["o_half", "o_zh", "o_lobe"]
"""Per-loop (OSC_LOBES,) float32, newest first: half-periods between band crossings
and between the zero crossings before them, lobes' mean |e|."""
ARRAYS = [
    *((n, (), np.float64) for n in F64),
    *((n, (), np.float32) for n in F32),
    *((n, (OSC_LOBES,), np.float32) for n in RINGS),
    ("o_n", (), np.int8),  # lobes on record
    ("o_k", (), np.int16),  # samples in the noise estimate (up to NOISE_WARM)
    ("o_j", (), bool),  # the previous sample was a move or a gap
    ("o_osc", (), bool),
]
"""The detector's per-loop arrays: name, shape after the slot, dtype (the monitor
allocates them with its own)."""


def clear(tb: LoopTable, s: int) -> None:
    """A new loop (or a reset): no lobe, no noise estimate."""
    for name in ("o_tc", "o_index", "o_z", "o_per"):
        getattr(tb, name)[s] = math.nan
    for name in ("o_var", "o_sign", "o_iae"):
        getattr(tb, name)[s] = 0.0
    tb.o_n[s], tb.o_k[s], tb.o_osc[s] = 0, 0, False


def forget_lobes(tb: LoopTable, s) -> None:
    """The count of lobes starts again (``s`` a slot or slots; the noise estimate stays):
    at a setpoint move or a gap (a setpoint toggled regularly makes the error a regular
    square wave, which is no oscillation of the loop), and at a rollback
    (:func:`service.engine.verify.fail`, or an advisory one accepted): the lobes on
    record are then the failed gains', whose ringing decays at the gains restored.
    Judged as theirs, that tail flagged the restored gains, which were then discredited
    (:func:`service.engine.verify.discredited`), and a later change failing on overshoot
    was kept, the loop left ringing. A sustained oscillation at the restored gains is
    flagged again after :data:`OSC_LOBES` lobes of its own."""
    tb.o_sign[s], tb.o_n[s], tb.o_osc[s] = 0.0, 0, False
    tb.o_tc[s] = tb.o_z[s] = math.nan


def noise_sigma(tb: LoopTable, slots, cold: bool | np.ndarray = False) -> np.ndarray:
    """The noise estimate's sigma (engineering units); 0 until it has its first
    :data:`NOISE_WARM` samples unless ``cold`` (per loop). The excitation gate's noise
    rule and the noise damping use it: a cold estimate is the loop's own motion as much as
    its noise, except for a loop sending only e, whose gate it keeps shut from the start."""
    sigma = np.sqrt(np.maximum(tb.o_var[slots], 0.0))
    return np.where(cold | (tb.o_k[slots] >= NOISE_WARM), sigma, 0.0)


def band(tb: LoopTable, slots: np.ndarray) -> np.ndarray:
    """The oscillation detector's hysteresis band, engineering units (inf: no scaling)."""
    with np.errstate(divide="ignore"):
        floor = OSC_MIN_BAND / tb.e_scale[slots]
    return np.maximum(OSC_NOISE_SIGMAS * np.sqrt(tb.o_var[slots]), floor)


def period(tb: LoopTable, s: int) -> float:
    """The oscillation's period as the detector measured it when it flagged loop ``s``,
    s: the last two half-periods between zero crossings."""
    return float(tb.o_per[s])


def _noise(tb: LoopTable, slots, e, prev_e, jumped) -> None:
    """One sample of the noise variance estimate (second differences of the error)."""
    # until the estimate has its first samples it is not frozen by lobes either (at
    # startup the band is the floor, and noise alone crosses it)
    k = tb.o_k[slots]
    usable = ~jumped & (tb.o_j[slots] == 0) & ((tb.o_n[slots] < 2) | (k < NOISE_WARM))
    d2 = e - 2.0 * prev_e + tb.o_e2[slots]
    var = np.where(usable, d2 * d2 / 6.0, tb.o_var[slots])
    forget = np.maximum(NOISE_FORGET, 1.0 / (1.0 + k))
    tb.o_var[slots] += forget * (var - tb.o_var[slots])
    tb.o_k[slots] = np.minimum(k + usable, NOISE_WARM)
    tb.o_e2[slots], tb.o_j[slots] = prev_e, jumped


def detect(tb: LoopTable, slots, t, e, prev_e, dt, jumped) -> np.ndarray:
    """One sample of the detector per loop (distinct slots, aligned arrays; ``jumped``: a
    setpoint move or a gap); returns the slots that start oscillating."""
    _noise(tb, slots, e, prev_e, jumped)
    h = band(tb, slots)
    tb.o_iae[slots] += np.abs(e) * dt
    sign = np.where(e > h, 1.0, np.where(e < -h, -1.0, 0.0))
    zc = ((e > 0) != (prev_e > 0)) & ~jumped
    if zc.any():
        ez, pz = e[zc], prev_e[zc]
        tb.o_z[slots[zc]] = t[zc] - dt[zc] * ez / (ez - pz)
    if jumped.any():
        forget_lobes(tb, slots[jumped])
    cur = tb.o_sign[slots]
    # the error leaves the band again on its lobe's side
    again = (sign == cur) & (sign != 0) & ~jumped & (np.abs(prev_e) <= h)
    # a partial lobe (after a move or a gap) that does so: a whole lobe from here (else
    # the first lobe of an oscillation that grows out of a move's slow tail would be
    # lost as partial)
    partial = np.isnan(tb.o_tc[slots])
    start = ((sign != 0) & (cur == 0)) | (again & partial)
    again &= ~partial
    crossed = (sign != 0) & (cur != 0) & (sign != cur)
    outside = sign != 0
    tb.o_seen[slots[outside]] = t[outside]
    # inside the band for three half-periods (one RL period before a lobe is known):
    # the oscillation, if any, is over
    quiet_for = np.where(tb.o_n[slots] > 0, 3.0 * tb.o_half[slots, 0], tb.period[slots])
    with np.errstate(invalid="ignore"):
        gone = (cur != 0) & ~outside & (t - tb.o_seen[slots] > quiet_for)
    if gone.any():
        g = slots[gone]
        tb.o_sign[g], tb.o_n[g], tb.o_osc[g], tb.o_tc[g] = 0.0, 0, False, math.nan
    if not (start.any() or again.any() or crossed.any()):
        return slots[:0]
    # where each lobe began, for the period: the error's last zero crossing (none since a
    # move: now) before it left the band; when it leaves the band again on the same side
    # (it came back in, perhaps across zero: noise, or an oscillation riding on an
    # offset, whose other half stays in the band), the last one before that exit
    z = tb.o_z[slots]
    began = np.where(np.isnan(z), t, z)
    tb.o_zs[slots[again]] = began[again]
    # the error came back across zero since its lobe began: that lobe is over (the other
    # half of the cycle stayed inside the band: an oscillation riding on an offset), a
    # new one on the same side begins here
    with np.errstate(invalid="ignore"):
        anew = again & (z > tb.o_tc[slots])
    if anew.any():
        a = slots[anew]
        tb.o_tc[a], tb.o_iae[a] = t[anew], 0.0
    if start.any():
        # a lobe that leaves the band from inside it is whole (the next crossing ends it
        # half a period later, as a crossing would have started it); one that starts
        # outside (a setpoint move, a gap) is partial
        clean = start & ~jumped & (np.abs(prev_e) <= h)
        s0 = slots[start]
        tb.o_sign[s0], tb.o_iae[s0] = sign[start], 0.0
        tb.o_tc[s0] = np.where(clean[start], t[start], math.nan)
        tb.o_zs[s0] = began[start]
    if not crossed.any():
        return slots[:0]
    return _crossed(tb, slots[crossed], t[crossed], dt[crossed], sign[crossed], began[crossed])


def _crossed(tb: LoopTable, s, tc, step, sign, began) -> np.ndarray:
    """Loops ``s`` crossed the band at plant times ``tc`` (the lobe before began at the
    zero crossing ``began``): record the lobe that ended and judge the last ones."""
    dur, zdur = tc - tb.o_tc[s], began - tb.o_zs[s]
    # the first lobe after a move or a gap is partial (o_tc NaN): not on record
    whole = np.isfinite(dur)
    w, dur, zdur, step = s[whole], dur[whole], zdur[whole], step[whole]
    for name in RINGS:
        ring = getattr(tb, name)
        ring[w, 1:] = ring[w, :-1]
    tb.o_half[w, 0], tb.o_zh[w, 0], tb.o_lobe[w, 0] = dur, zdur, tb.o_iae[w] / dur
    tb.o_n[w] = np.minimum(tb.o_n[w] + 1, OSC_LOBES)
    tb.o_sign[s], tb.o_tc[s], tb.o_zs[s], tb.o_iae[s] = sign, tc, began, 0.0
    enough = tb.o_n[w] >= 2
    full, step = w[enough], step[enough]
    if not full.size:
        return full
    half, lobe, h = tb.o_half[full].astype(np.float64), tb.o_lobe[full], band(tb, full)
    zh = tb.o_zh[full].astype(np.float64)
    warm = (tb.o_k[full] >= NOISE_WARM) & (half[:, :2].min(axis=1) >= OSC_MIN_SAMPLES * step)
    sustained, r3 = _sustained(tb.o_n[full] >= OSC_LOBES, half, lobe, h, step)
    # the growing test: two lobes (at least OSC_GROWTH_SAMPLES each), regular, the newer
    # above the band and OSC_GROWTH times the older, the older above half the band; with
    # a third on record, growing over the period as well (a decaying response whose
    # small lobe follows a large one is not growing)
    r2 = _regularity(half[:, :2])
    growing = (
        (r2 > 1.0)
        & (half[:, :2].min(axis=1) >= OSC_GROWTH_SAMPLES * step)
        & (lobe[:, 0] >= h)
        & (lobe[:, 0] >= OSC_GROWTH * lobe[:, 1])
        & (lobe[:, 1] >= 0.5 * h)
        & ((tb.o_n[full] < OSC_LOBES) | (lobe[:, 0] >= lobe[:, 2]))
    )
    osc = warm & (sustained | growing)
    tb.o_index[full] = np.where(sustained | ~growing, r3, r2)
    new = osc & ~tb.o_osc[full]
    tb.o_per[full[new]] = zh[new, 0] + zh[new, 1]
    tb.o_osc[full] = osc
    return full[new]


def _sustained(three, half, lobe, h, step) -> tuple[np.ndarray, np.ndarray]:
    """The sustained test of loops with ``OSC_LOBES`` lobes on record (``three``; rows of
    the newest first) and their regularity index r (NaN: fewer lobes)."""
    half = half.copy()
    # the oldest lobe may have begun before the oscillation did (noise carried the error
    # out of the band first): longer than the newer ones, its length is no
    # irregularity and its mean |e| is diluted by the time before (not held against the
    # band)
    newer = half[:, :-1].mean(axis=1)
    lead = half[:, -1] > newer
    half[:, -1] = np.minimum(half[:, -1], newer)
    # lobes that grow one after the other: an unstable loop, whose oldest lobe may still
    # be half inside the band
    growing = (lobe[:, 0] > lobe[:, 1]) & (lobe[:, 1] > lobe[:, 2])
    r = _regularity(half)
    osc = (
        three
        & (r > 1.0)
        & (half[:, -1] >= OSC_MIN_SAMPLES * step)
        # the newest lobe above the band, the older ones (still rising out of the noise)
        # above half of it
        & (lobe[:, 0] >= h)
        & (lobe[:, 1] >= 0.5 * h)
        & (lead | (lobe[:, 2] >= 0.5 * h) | growing)
        & (lobe[:, 0] >= OSC_DECAY * lobe[:, 2])
    )
    return osc, np.where(three, r, math.nan)


def _regularity(half: np.ndarray) -> np.ndarray:
    """Thornhill's r = mean / (3 std) of each row of half-periods (at most 10)."""
    spread = half.std(axis=1)
    r = np.where(spread > 0, half.mean(axis=1) / (3.0 * np.maximum(spread, 1e-300)), 10.0)
    return np.minimum(r, 10.0)
