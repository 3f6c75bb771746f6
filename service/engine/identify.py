"""Closed-loop identification of a loop's process model: pure numerics, no engine state.

An *event* is a window of one loop's closed-loop data (sample times, setpoint,
measurement and controller output) that starts at a setpoint move, or at an operator's
step of the output in manual (open-loop data, a bump test), and ends at the next one
(or when it grows too long). :func:`assess` fits one first-order-plus-dead-time model
from the controller output to the measurement over a segment of consecutive events::

    pv(t_k) = b + K x_k + c a^k,    tau x'(t) = u(t - theta) - u(t0) - x(t),    x(t0) = 0

(a = exp(-h / tau), h the sample period: the offset ``b`` absorbs the operating point
and, when the output is reconstructed from the PI law, the unknown integral term; the
free transient ``c a^k``, one per segment, a plant not yet at rest when it opens). The
fit is an output-error fit: the model is simulated from the controller output alone,
so measurement noise does not bias it as it would an equation-error (ARX) fit, and the
controller's reaction to noise is small where the move is large against the noise
(which the acceptance rules require).

Two steps: a grid over (tau, theta), each point linear in (b, K, c) and solved in closed
form, vectorised over the grid; then :func:`scipy.optimize.least_squares` refines the
best point over (K, log tau, theta, b, c). An integrating model
``K/s e^{-theta s}`` is fitted the same way and compared.

The model is confident when it explains the segment, enough of its events show the
response above the noise, K and tau are pinned down (standard errors from the Jacobian)
and the model fitted without the last event predicts it (:func:`assess`).

The fit itself (the data as it sees them, grid search, refinement, the integrating
alternative) is :mod:`service.engine.foptd_fit`. Sampling assumption: the samples
follow a uniform clock, give or take a gateway's jitter (each row placed at the grid
sample nearest its time; the recorder's rows may each be the mean of several:
:func:`~service.engine.foptd_fit.recorded`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from service.engine.foptd_fit import MIN_R2, fit_windows, predict, recorded
from service.units import RAMP_GAP

MIN_SAMPLES = 12
"""Fewest samples in an event worth fitting."""
MIN_SNR = 3.0
"""Smallest ratio of the modelled response (peak to peak) to the residual noise (rms)."""
MAX_REL_SE = 0.1
"""Largest relative standard error of K of the joint fit of a confident model."""
MAX_TAU_SE = 0.17
"""Largest relative standard error of tau: looser than K's, whose error is 2-10x smaller
on the same data (closed-loop data pin the gain down first; tau trades off against the
dead time). Measured on the bar's loops, seeds 0-2 (docs/identification.md): 0.15, 0.17,
0.20 identify 55-57, 57 and 58 of 60 from their first 4 moves."""
LUMP_EVENTS = 3
"""Events a lumped model needs (:data:`LUMP_THETA`): one more than :data:`MIN_EVENTS`.
From two ramps over 3 tau (noise 5 % of the move) the model came mid-way through the
second ramp's response with K 12 % and the lag 19 % low, 4 and 2 of their standard
errors (tests/test_identify.py's loop); needing three, its first model came at the
fifth ramp, K 1.5 % and the lag 2 % off."""
MAX_PREDICTION = 1.5
"""Consistency: the model of the earlier events must predict the last event's PV within
this many times the noise (rms)."""
PREDICTION_FLOOR = 0.01
"""Consistency on (nearly) noise-free data: the prediction error is counted against at
least this share of the typical move. There the residual is the linear model's own
error on a nonlinear plant, not noise, and its size depends on how the rows are
weighted: on the two-tank demo (noise 0) the earlier events' model predicted the third
with 0.02 cm, 2.3x the residual of 0.008 cm, and the model came 5 simulated minutes
later than with a prediction held to 0.2% of the 10 cm move. Under the bar's 1% noise
(moves of 5-25) the floor is below the noise and changes nothing."""
MIN_EVENTS = 2
"""Excited events needed for a confident model."""
RAMP_SHOWN = 1.0
"""An event whose setpoint kept moving for longer than this many times the model's
tau + theta (a ramp slower than the loop) excites nothing: a FOPTD follows a slow ramp
by tau + theta, which the data tell, but not tau from theta (fits of ramps over 3-11 tau
were confident and wrong, tau + theta taken as tau: docs/identification.md). A faster
ramp shows both, as a step does (ramps over 0.3-1 tau: K, tau within 3 %)."""
LUMP_THETA = 0.3
"""A *lumped* model: where only ramps slower than the loop excite it, the events they show
pin down K and tau + theta, not the split, and the model is that lag split with this
share of dead time (theta/tau 0.43). Its tuning (:mod:`service.engine.first_tuning`)
then scores a step-test MSE of at most 0.0013-0.007 on every true split with theta/tau
up to 1 (tau + theta 0.275-2 agent units), 0.031 up to theta/tau 3; with the lag taken
as tau, up to 0.026 and 0.07 (docs/identification.md, Lumped models)."""

OP_RAMP_PART = 0.75
"""Share of an output ramp's excursion whose time :func:`_op_ramp` measures (the whole
would hang on the last noisy samples of a valve's position feedback)."""

IMPRECISE = "K or tau not pinned down"
"""The verdict of a model that passes every check but precision."""
DISAGREE = "events disagree"
"""The verdict of a precise model that fails only the consistency test (a drifting plant)."""
INTEGRATING = "integrating"
"""The verdict of a segment an integrating model ``K/s e^{-theta s}`` fits better."""
_WHAT_WORKS = "a setpoint step or an output step in manual, op in the samples, identifies it"
"""What the operator can do where the loop's own moves do not identify it (a bump test)."""
_NOT_LINEAR = (
    "the data are not one linear process: an output at a limit the samples do not show "
    "(send op, or the saturated flag), a disturbance, a change of the plant"
)
"""What a poor fit means to the user."""


@dataclass
class EventFit:
    """One event (a setpoint move, or an output step in manual, and the data up to the
    next) as identification saw it."""

    t0: float
    t1: float
    n: int
    move: float
    """The setpoint move of the event (engineering units, signed): from the setpoint before
    it to the event's last (a ramp's whole run)."""
    ramp_s: float = 0.0
    """Seconds the setpoint kept moving after the event's first change, or an output step's
    output (0: a step; inf: still moving at the event's end)."""
    snr: float = math.nan
    """Peak-to-peak response the model shows in the event, in multiples of the noise."""
    excited: bool = False
    op_move: float = 0.0
    """The output step an operator made in manual that opened the event, from the output
    before it to the event's last (a step in several parts: the whole; output units; 0:
    a setpoint move's event)."""

    def as_dict(self) -> dict:
        return {k: _num(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> EventFit:
        names = cls.__dataclass_fields__
        return cls(**{k: (math.nan if v is None else v) for k, v in d.items() if k in names})


@dataclass
class Model:
    """The FOPTD model of a segment and how far to trust it."""

    k: float
    tau: float
    theta: float
    noise: float
    """Residual rms (PV units): the measurement noise."""
    move: float
    """Typical setpoint move (median |move| of the excited events; of an output step, the
    PV change it makes, |K op_move|)."""
    r2: float
    k_rse: float
    tau_rse: float
    integrating: bool = False
    slope: float = 0.0
    """The integrating alternative's K (PV units per output unit per second): the
    process's, when ``integrating`` (the FOPTD's K and tau then say nothing)."""
    theta_i: float = 0.0
    """The integrating alternative's dead time (s)."""
    events: int = 0
    """Excited events the model comes from."""
    prediction: float = math.inf
    """Rms error (in noise units) with which the model of the earlier events predicts
    the last one."""
    confidence: float = 0.0
    """0..1: excitation x precision x consistency."""
    confident: bool = False
    lumped: bool = False
    """tau and theta are tau + theta split by :data:`LUMP_THETA` (the data showed the lag
    only), and ``tau_rse`` is the lag's."""

    def as_dict(self) -> dict:
        return {k: _num(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> Model:
        names = cls.__dataclass_fields__
        return cls(**{k: (math.inf if v is None else v) for k, v in d.items() if k in names})

    @classmethod
    def load(cls, d: dict | None) -> Model | None:
        """:meth:`from_dict`, or None for None (a snapshot's missing model)."""
        return None if d is None else cls.from_dict(d)


@dataclass
class Assessment:
    events: list[EventFit]
    model: Model | None = None
    why: str = ""
    """Why the model is not confident ('' when it is)."""


def _num(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def reconstruct_op(t, e, kp, ki) -> np.ndarray:
    """The controller output of a parallel PI ``u = kp e + I``, ``I' = ki e`` (backward
    Euler on the sample times), bumpless on gain changes (a change of kp moves I so that
    u does not jump), from I = 0 at the first sample: the output up to a constant, which
    the fit's offset absorbs. Assumes the DCS runs the PI at (about) the sample period,
    with no feedforward, bias change or output tracking in the window."""
    t, e, kp, ki = (np.asarray(v, np.float64) for v in (t, e, kp, ki))
    dt = np.diff(t, prepend=t[:1])
    # bumpless: I jumps by -(kp_k - kp_{k-1}) e_{k-1} at a change of kp
    dkp = np.diff(kp, prepend=kp[:1])
    e_prev = np.concatenate([e[:1], e[:-1]])
    integral = np.cumsum(ki * e * dt - dkp * e_prev)
    return kp * e + integral


def screen(t, pv, op) -> str:
    """Why a window cannot be fitted at all ('' if it can)."""
    n = len(t)
    if n < MIN_SAMPLES:
        return f"too few samples ({n} < {MIN_SAMPLES})"
    t, pv, op = (np.asarray(x, np.float64) for x in (t, pv, op))
    if not (np.isfinite(t).all() and np.isfinite(pv).all() and np.isfinite(op).all()):
        return "non-finite data"
    if not (np.diff(t) > 0.0).all():  # a window of no duration: nothing to fit
        return "sample times not increasing (a new plant clock inside the segment)"
    # stuck: one value for most of the window (a PV in coarse steps, an integer register
    # or an ADC's, repeats many samples in a row, but moves from value to value)
    changes = np.flatnonzero(np.diff(pv) != 0.0)
    if np.diff(np.r_[-1, changes, n - 1]).max() > 0.5 * n:
        return "measurement frozen (stuck transmitter?)"
    if np.ptp(op) == 0.0:
        return "controller output did not move"
    return ""


def assess(
    t,
    sp,
    pv,
    op,
    starts: list[int],
    start: tuple[float, float] | None = None,
    last: int = 1,
    op_sent: bool = True,
    registered: float = 0.0,
) -> Assessment:
    """Identify from one contiguous segment of data (no gap or saturated sample inside,
    in auto or in manual with the output sent) whose events (setpoint moves, or output
    steps in manual: those whose setpoint is the one before, :func:`_bump`) start at the
    indices ``starts``; the last event runs to the end of the data. Rows may be the
    recorder's means of several samples (:func:`recorded`; ``last``: the samples the last
    row holds; ``op_sent``: the output is the gateway's, not rebuilt from the PI law;
    ``registered``: the loop's registered sample period, :func:`foptd_fit.sample_period`).

    One FOPTD model is fitted to the whole segment (one offset, one initial transient:
    far better determined than a fit per event). Each event is then judged by the
    response the model shows in it against the noise (a move too small for the noise
    excites nothing), and the model fitted without the last event must predict that
    event (consistency between events). Confident when :data:`MIN_EVENTS` events are
    excited, the fit explains the data (:data:`MIN_R2`), K and tau are pinned down
    (:data:`MAX_REL_SE`, :data:`MAX_TAU_SE`), the prediction holds (:data:`MAX_PREDICTION`) and an
    integrating model does not fit better.
    """
    t, sp, pv, op = (np.asarray(x, np.float64) for x in (t, sp, pv, op))
    starts = _ramps_whole(t, sp, op, starts)
    bounds = [*starts, t.size]
    events = [
        EventFit(float(t[a]), float(t[b - 1]), b - a, 0.0, ramp_s=_op_ramp(t, sp, op, a, b),
                 op_move=float(op[b - 1] - op[a - 1]))
        if _bump(sp, a)
        else EventFit(
            t0=float(t[a]), t1=float(t[b - 1]), n=b - a,
            move=float(sp[b - 1] - sp[a - 1]) if a > 0 else 0.0, ramp_s=_ramp(t, sp, a, b),
        )
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]  # fmt: skip
    out = Assessment(events=events)
    if len(starts) < MIN_EVENTS:
        out.why = (
            f"waiting for setpoint moves or output steps in manual ({len(starts)} of "
            f"{MIN_EVENTS} seen)"
        )
        return out
    first = fitted_from(starts)
    t, sp, pv, op = t[first:], sp[first:], pv[first:], op[first:]
    bounds = [b - first for b in bounds]
    out.why = screen(t, pv, op)
    if out.why:
        return out
    whole = recorded(t, pv, op, last, registered)
    joint = fit_windows([whole], start)
    pred = joint.model[0]
    lag = joint.tau + joint.theta
    strict, slow = [], 0
    for ev, a, b in zip(events, bounds[:-1], bounds[1:], strict=True):
        ev.snr = float(np.ptp(pred[a:b])) / max(joint.noise, 1e-300) if b > a else 0.0
        shows = ev.ramp_s <= RAMP_SHOWN * lag
        strict.append(bool(ev.snr >= MIN_SNR and shows))
        slow += not shows
    # where only ramps slower than the loop stand out of the noise: K and the lag
    seen = [ev.snr >= MIN_SNR for ev in events]
    lumped = sum(strict) < MIN_EVENTS and sum(seen) >= LUMP_EVENTS
    data = (t, pv, bounds, whole, slow, op_sent)
    judged = _judged(joint, events, seen if lumped else strict, lumped, *data)
    if lumped and judged[1]:  # a lumped attempt that fails is reported as none was made
        judged = _judged(joint, events, strict, False, *data)
    out.model, out.why = judged
    return out


def _judged(
    joint, events, excited, lumped, t, pv, bounds, whole, slow, op_sent
) -> tuple[Model, str]:
    """:func:`assess`'s model of the segment fitted as ``joint`` (:func:`fit_windows`),
    with the events flagged ``excited`` (``lumped``: its split assumed,
    :data:`LUMP_THETA`), tested for consistency and judged: (model, why not confident).
    ``t``, ``pv``: the rows fitted, ``bounds`` the events' first rows in them and their
    end, ``whole`` their :func:`recorded` window, ``slow`` how many events ramp slower
    than the loop."""
    for ev, flag in zip(events, excited, strict=True):
        ev.excited = bool(flag)
    lag = joint.tau + joint.theta
    m = Model(
        k=joint.k, tau=(1.0 - LUMP_THETA) * lag if lumped else joint.tau,
        theta=LUMP_THETA * lag if lumped else joint.theta, noise=joint.noise,
        move=float(np.median([abs(ev.move or joint.k * ev.op_move) for ev in events
                              if ev.excited] or [0.0])),  # fmt: skip
        r2=joint.r2, k_rse=joint.k_rse, tau_rse=joint.lag_rse if lumped else joint.tau_rse,
        integrating=joint.integrating, slope=joint.slope, theta_i=joint.theta_i,
        events=sum(excited), lumped=lumped,
    )  # fmt: skip
    # consistency: the model of the data before the last excited event that has run the
    # model's theta + tau predicts it and what follows (a quiet event, or the first
    # samples of a new one, test next to nothing: docs/identification.md)
    tested = max(
        (i for i, ev in enumerate(events) if ev.excited and t[-1] - t[bounds[i]] >= lag),
        default=0,
    )
    cut = bounds[tested]
    if cut >= MIN_SAMPLES and m.events >= MIN_EVENTS:
        early = fit_windows([whole.head(cut)], (joint.tau, joint.theta))
        b, c = early.params[3], early.params[4]
        miss = (predict(early.params, whole, b, c) - pv)[cut:]
        if whole.count is not None:  # in one sample's noise, as the residual
            miss = miss * np.sqrt(whole.count[cut:])
        rms = float(np.sqrt(np.mean(miss**2)))
        m.prediction = rms / max(joint.noise, PREDICTION_FLOOR * m.move, 1e-300)
    why = _verdict(m, m.events, len(events), slow, op_sent)
    worst = max(m.k_rse / MAX_REL_SE, m.tau_rse / MAX_TAU_SE)
    precision = min(1.0, max(0.0, 1.5 - 0.5 * worst))
    consistency = min(1.0, max(0.0, (2.0 * MAX_PREDICTION - m.prediction) / MAX_PREDICTION))
    m.confidence = float(
        min(1.0, m.events / MIN_EVENTS) * precision * consistency * (m.r2 >= MIN_R2)
    )
    m.confident = not why
    return m, why


def fitted_from(starts: list[int]) -> int:
    """The first sample :func:`assess` fits, given the events' starts: the sample before
    the first move (the input at rest before it: the window's first input is held before
    the window, so starting at the move would hide the controller's proportional kick and
    bias tau up, K up and theta down)."""
    return max(starts[0] - 1, 0)


def precise(m: Model) -> bool:
    """Whether K and tau are pinned down (:data:`MAX_REL_SE`, :data:`MAX_TAU_SE`)."""
    return m.k_rse <= MAX_REL_SE and m.tau_rse <= MAX_TAU_SE


def _bump(sp: np.ndarray, a: int) -> bool:
    """Whether the event from row ``a`` is an output step in manual: the recorder holds
    the setpoint of before manual there (:func:`service.engine.watch.record`), where a
    setpoint move's event starts with a new one."""
    return a > 0 and sp[a] == sp[a - 1]


def _ramp(t: np.ndarray, sp: np.ndarray, a: int, b: int) -> float:
    """:attr:`EventFit.ramp_s` of the event in rows ``a:b``."""
    changed = np.flatnonzero(sp[a + 1 : b] != sp[a : b - 1])
    if not changed.size:
        return 0.0
    last = a + 1 + int(changed[-1])
    return math.inf if b - 1 - last < RAMP_GAP else float(t[last] - t[a])  # still ramping


def _ramps_whole(t, sp, op, starts: list[int]) -> list[int]:
    """``starts`` without those that cut an output ramp: an operator's ramp whose every
    sample changes the output by more than a step's threshold opens an event every
    :data:`~service.engine.watch.MIN_EVENT_SAMPLES`; a piece still ramping at its end and
    the output step after it are one event, the whole ramp (:func:`_op_ramp` judges it)."""
    out = list(starts[:1])
    for b in starts[1:]:
        a = out[-1]
        if not (_bump(sp, a) and _bump(sp, b) and _op_ramp(t, sp, op, a, b) == math.inf):
            out.append(b)
    return out


def _op_ramp(t: np.ndarray, sp: np.ndarray, op: np.ndarray, a: int, b: int) -> float:
    """:attr:`EventFit.ramp_s` of the output step in rows ``a:b`` (an operator holding a
    raise/lower button ramps the output): over its rows in manual (those with the setpoint
    of before manual, :func:`_bump`), the time the output took to cover
    :data:`OP_RAMP_PART` of its largest excursion from the row before, scaled to the
    whole (a step: 0); inf while the excursion still grows by more than the rest of it
    within the last :data:`~service.units.RAMP_GAP` rows."""
    held = sp[a:b] == sp[a - 1]
    end = a + (int(np.argmin(held)) if not held.all() else b - a)  # manual rows: a..end-1
    away = np.abs(op[a:end] - op[a - 1])
    size = float(away.max())
    if not size > 0.0:
        return 0.0
    if end == b and away[-1] - away[max(0, end - a - 1 - RAMP_GAP)] > (1.0 - OP_RAMP_PART) * size:
        return math.inf
    reach = a + int(np.argmax(away >= OP_RAMP_PART * size))
    return float(t[reach] - t[a]) / OP_RAMP_PART


def _verdict(m: Model, excited: int, n_events: int, slow: int = 0, op_sent: bool = True) -> str:
    if m.integrating:
        return (
            f"{INTEGRATING}: K/s e^(-theta s) fits better than an FOPTD model (K "
            f"{m.slope:.3g} PV units per output unit per s, theta {m.theta_i:.3g} s)"
        )
    if excited < MIN_EVENTS and slow:
        return (
            f"setpoint or output ramp slower than the loop ({slow} of {n_events} events "
            f"ramp longer than tau + theta, {m.tau + m.theta:.3g} s: tau and dead time not "
            f"separable; {_WHAT_WORKS})"
        )
    if excited < MIN_EVENTS:
        return (
            f"move too small for the noise ({excited} of {n_events} events show a "
            f"response {MIN_SNR:g}x the noise {m.noise:.3g}; {MIN_EVENTS} needed; "
            f"{_WHAT_WORKS})"
        )
    if m.r2 < MIN_R2:  # before the sign: a model that does not fit says nothing of it
        return f"poor fit (R2 {m.r2:.2f} < {MIN_R2:g}; {_NOT_LINEAR})"
    if not m.k > 0.0 and not op_sent:
        # the output rebuilt from the PI law flips with the PV for either action: the
        # sign says the data are not one linear process, not which action the block has
        return f"process gain {m.k:.3g} < 0 from an output rebuilt from the PI law ({_NOT_LINEAR})"
    if not m.k > 0.0:
        return (
            f"process gain {m.k:.3g} has the wrong sign for the registered controller "
            "action (the DCS block's action is probably the other one: register the loop "
            "again with the other 'action')"
        )
    if not precise(m):
        return f"{IMPRECISE} (rel. s.e. {m.k_rse:.2f}, {m.tau_rse:.2f})"
    if not m.prediction <= MAX_PREDICTION:
        return (
            f"{DISAGREE} (the earlier events' model predicts the last with "
            f"{m.prediction:.2f}x the noise)"
        )
    return ""
